"""A run directory as an object: ``drago.Run(path)`` reads its config, results, logs and checkpoints on demand."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from drago.training.checkpoint import load_task_checkpoint
from drago.training.rundir import (
    RunCheckpoint,
    RunDirError,
    finished_task_checkpoints,
    is_complete,
    read_run_config,
    read_summary,
    task_checkpoint_path,
)

LOG_FILES = {"train": "train.csv", "eval": "eval.csv", "timing": "timing.csv"}


class Run:
    """A run directory, read on demand: ``drago.Run("runs/minigrid-cpu/drago/seed1")``.

    Attributes:
        path: the run directory.
        config: the resolved config it was started with.

    Raises:
        RunDirError: not a run directory; drago.config.ConfigError: an invalid ``config.yaml``.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.config = read_run_config(self.path)

    def __repr__(self) -> str:
        done = len(self.tasks)
        return (f"Run({str(self.path)!r}: {self.config.method.name}, seed {self.config.train.seed}, "
                f"{done}/{len(self.config.env.tasks)} tasks done)")

    @property
    def summary(self) -> dict[str, Any] | None:
        """``summary.json``: per-task results; None before the first task finished."""
        return read_summary(self.path)

    @property
    def tasks(self) -> list[dict[str, Any]]:
        """The finished tasks' summary entries (final evaluation, steps, wall and CPU time, peak memory)."""
        return list((self.summary or {}).get("tasks", []))

    @property
    def complete(self) -> bool:
        return is_complete(self.path)

    @property
    def is_transfer(self) -> bool:
        return self.config.transfer.checkpoint is not None

    def metrics(self, log: str = "eval", as_frame: bool | None = None) -> Any:
        """A log of the run: ``"train"`` (one row per learner episode), ``"eval"`` or ``"timing"``.

        Returns a pandas DataFrame when pandas is installed (or ``as_frame=True``), else a dict of numpy
        arrays by column (numbers as floats, blanks as NaN; text columns as strings). Empty if the log
        does not exist yet.
        """
        if log not in LOG_FILES:
            raise ValueError(f"unknown log '{log}'; choose one of: {', '.join(LOG_FILES)}")
        file = self.path / LOG_FILES[log]
        rows: list[dict[str, str]] = []
        if file.is_file():
            with file.open(newline="") as handle:
                rows = list(csv.DictReader(handle))
        if as_frame is None:
            try:
                import pandas  # noqa: F401
                as_frame = True
            except ImportError:
                as_frame = False
        columns = list(rows[0]) if rows else []
        if as_frame:
            import pandas as pd

            return pd.DataFrame(rows, columns=columns).apply(pd.to_numeric, errors="ignore") if rows else pd.DataFrame()

        def column(name: str) -> np.ndarray:
            values = [r[name] for r in rows]
            try:
                return np.array([float(v) if v != "" else np.nan for v in values])
            except ValueError:
                return np.array(values)

        return {name: column(name) for name in columns}

    def checkpoints(self) -> list[RunCheckpoint]:
        """The finished tasks' checkpoints, in stage order."""
        return finished_task_checkpoints(self.path, self.config)

    def checkpoint(self, stage: int) -> Path:
        """The task checkpoint written after ``stage`` (1-based).

        Raises:
            RunDirError: a stage out of range or not finished yet.
        """
        tasks = self.config.env.tasks
        if not 1 <= stage <= len(tasks):
            raise RunDirError(f"stage {stage} is out of range: {self.path} has {len(tasks)} tasks")
        path = task_checkpoint_path(self.path, tasks, stage)
        if not path.is_file():
            raise RunDirError(f"{self.path} has not finished stage {stage} ({tasks[stage - 1]}) yet")
        return path

    def world_model(self, stage: int, device: str = "cpu") -> Any:
        """The world model after ``stage`` (a torch module in eval mode; :func:`drago.load_world_model`
        gives a numpy predictor of the same checkpoint)."""
        return load_task_checkpoint(self.checkpoint(stage), device).world_model.eval()


class Record(Run):
    """A run's record (``*.json.gz``, docs: Command line, "Records"), read like a run directory:
    ``drago.Record("results/grid/drago/seed1.json.gz")``. Its logs, summary and the evaluations made from
    its checkpoints are there; the checkpoints themselves are not.

    Attributes:
        record_path: the record file.
        protocol: what decides the unit's results, with its digest.
        provenance: drago's version, the commit, the machine, threads, device and when it was recorded.
        path: a private folder the record's files are read from (removed with the object).

    Raises:
        drago.training.records.RecordError: a corrupt record, or one of another format version (one line).
    """

    def __init__(self, path: str | Path):
        import shutil
        import tempfile
        import weakref

        from drago.training.records import materialize, read_record

        record = read_record(path)
        self.record_path = Path(path)
        self.protocol: dict[str, Any] = record["protocol"]
        self.provenance: dict[str, Any] = record["provenance"]
        folder = tempfile.mkdtemp(prefix="drago-record-")
        weakref.finalize(self, shutil.rmtree, folder, True)
        super().__init__(materialize(record, folder))

    def __repr__(self) -> str:
        return f"Record({str(self.record_path)!r}: {self.config.method.name}, seed {self.config.train.seed})"

    def evaluation(self, name: str) -> list[dict[str, str]]:
        """The rows of an evaluation file the unit recorded: ``coverage``, ``zero_shot``, ``components``,
        ``swap``, ``costs`` or ``retention`` (empty when the record has none)."""
        file = self.path / f"{name}.csv"
        if not file.is_file():
            return []
        with file.open(newline="") as handle:
            return list(csv.DictReader(handle))

    def transfers(self) -> list[Run]:
        """The unit's transfer runs, each read like a run directory."""
        return [Run(config.parent) for config in sorted((self.path / "transfer").glob("*/config.yaml"))]

    def checkpoints(self) -> list[RunCheckpoint]:
        return []

    def checkpoint(self, stage: int) -> Path:
        raise RunDirError(f"{self.record_path} is a record: it keeps no checkpoints (they stay on the machine "
                          "that trained the run)")
