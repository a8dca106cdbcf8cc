"""Run logging: CSV files (one row per iteration / evaluation), TensorBoard events, Weights & Biases
(optional, :mod:`drago.training.tracking`), console echo.

CSV files hold only values that are reproducible from the seed, so two runs with the same seed on
the same CPU write identical files; wall-clock figures go to ``timing.csv`` and ``summary.json``.
"""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tqdm import tqdm

if TYPE_CHECKING:
    from drago.training.tracking import WandbTracker


def _format(value: Any) -> Any:
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    return value


def scalars(kind: str, row: dict[str, Any]) -> dict[str, float | int]:
    """The scalars of a log row as ``{tag: value}``: what TensorBoard and Weights & Biases both receive.

    Training rows become ``train/KEY``, evaluations ``eval/TASK/KEY``; timing rows (wall clock, not
    reproducible) and the task index stay in the CSV files only.
    """
    if kind == "timing":
        return {}
    prefix = kind if kind == "train" else f"{kind}/{row.get('task', '')}"
    return {f"{prefix}/{key}": value for key, value in row.items()
            if isinstance(value, (int, float)) and not isinstance(value, bool) and key != "task_index"}


class CSVLog:
    """Append-only CSV whose header grows when a later row brings new columns (e.g. a reviewer)."""

    def __init__(self, path: Path):
        self.path = path
        self.columns: list[str] = []
        self.rows = 0
        if path.exists():
            with path.open(newline="") as handle:
                reader = csv.reader(handle)
                header = next(reader, None)
                self.columns = header or []
                self.rows = sum(1 for _ in reader)

    def write(self, row: dict[str, Any]) -> None:
        new = [k for k in row if k not in self.columns]
        if new:
            self._rewrite_with(self.columns + new)
        with self.path.open("a", newline="") as handle:
            csv.DictWriter(handle, fieldnames=self.columns).writerow({k: _format(v) for k, v in row.items()})
        self.rows += 1

    def _rewrite_with(self, columns: list[str]) -> None:
        old = self.read()
        self.columns = columns
        with self.path.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns)
            writer.writeheader()
            writer.writerows(old)

    def read(self) -> list[dict[str, str]]:
        if not self.path.exists():
            return []
        with self.path.open(newline="") as handle:
            return list(csv.DictReader(handle))

    def truncate(self, rows: int) -> None:
        """Drop rows written after a checkpoint, so a resumed run does not log them twice."""
        kept = self.read()[:rows]
        if self.columns:
            with self.path.open("w", newline="") as handle:
                writer = csv.DictWriter(handle, fieldnames=self.columns)
                writer.writeheader()
                writer.writerows(kept)
        self.rows = len(kept)


class RunLogger:
    """All of a run's outputs except checkpoints; ``positions`` lets a resumed run cut back the logs."""

    FILES = ("train", "eval", "timing")

    def __init__(self, run_dir: Path, tensorboard: bool, purge_step: int | None = None,
                 wandb: WandbTracker | None = None):
        self.run_dir = run_dir
        self._wandb = wandb
        self.csv = {name: CSVLog(run_dir / f"{name}.csv") for name in self.FILES}
        self.console = (run_dir / "console.log").open("a")
        self._tb = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            # purge_step drops events a killed run wrote after its last checkpoint.
            self._tb = SummaryWriter(str(run_dir / "tb"), purge_step=purge_step)

    def positions(self) -> dict[str, int]:
        return {name: log.rows for name, log in self.csv.items()}

    def restore(self, positions: dict[str, int]) -> None:
        for name, rows in positions.items():
            self.csv[name].truncate(rows)

    def log(self, kind: str, row: dict[str, Any], global_step: int) -> None:
        self.csv[kind].write(row)
        values = scalars(kind, row)
        if self._tb is not None:
            for tag, value in values.items():
                self._tb.add_scalar(tag, value, global_step)
        if self._wandb is not None and values:
            self._wandb.log(values, global_step)

    def print(self, message: str) -> None:
        """Echo to the console (above any progress bar) and keep a copy in console.log."""
        tqdm.write(message, file=sys.stdout)
        self.console.write(message + "\n")
        self.console.flush()

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
        if self._wandb is not None:
            self._wandb.close()
        self.console.close()
