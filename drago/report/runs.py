"""Reading run directories for a report: which runs a path names, and what each one holds."""

from __future__ import annotations

import contextlib
import csv
import math
import os
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drago.config import Config
from drago.envs import get_domain, is_domain
from drago.envs.tasks import GRID_TASKS
from drago.training.records import RECORD_SUFFIX, find_records, idle_settings, materialize, read_record
from drago.training.rundir import (CONFIG_FILE, RESOLVED_AT_START, TRANSFER_FOLDER, RunDirError, flat_settings,
                                   read_run_config, read_summary)

EVAL_FILE = "eval.csv"
FRACTION_LABEL = "fraction of DP optimum"
RETURN_LABEL = "return"
EVAL_COLUMNS = ("task", "env_step", "fraction_of_optimal")


class ReportError(RunDirError):
    """A run or path a report cannot use; the message is one line (the CLI prints it, exit 2)."""


def find_run_dirs(paths: Iterable[str | Path]) -> list[Path]:
    """ReportedRun directories named by ``paths``: each path is a run (it has ``config.yaml``) or a folder
    whose run directories below it are taken, in sorted order. The search does not look inside a run
    directory: what lies there (``transfer/`` runs) is another kind of experiment, which
    :func:`find_transfer_dirs` finds. Duplicates are dropped.

    Raises:
        ReportError: A path that does not exist, or is neither a run nor holds one.
    """
    found: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise ReportError(f"{path} does not exist")
        if (path / CONFIG_FILE).is_file():
            below = [path]
        elif path.is_dir():
            below = []
            for folder, subfolders, files in os.walk(path):
                if CONFIG_FILE in files:
                    below.append(Path(folder))
                    subfolders.clear()
                else:
                    subfolders.sort()
            if not below:
                raise ReportError(f"{path} is not a drago run directory (no {CONFIG_FILE}) and holds none below it")
        else:
            raise ReportError(f"{path} is not a drago run directory (no {CONFIG_FILE})")
        found.extend(p for p in below if p not in found)
    if not found:
        raise ReportError("no run directories given")
    return found


@contextlib.contextmanager
def opened_runs(paths: Iterable[str | Path]) -> Iterator[list[tuple[Path, str]]]:
    """``(run directory, how to name it)`` for every run that ``paths`` name, run directories and records
    alike: a record (``*.json.gz``, or a folder holding records) is materialized into a temporary record view
    that lives as long as the ``with`` block and is named by its record file.

    Raises:
        ReportError: a path without runs or records (see :func:`find_run_dirs`).
        drago.training.records.RecordError: a corrupt record or one of another format version (one line).
    """
    paths = [Path(p) for p in paths]
    with tempfile.TemporaryDirectory(prefix="drago-records-") as scratch:
        found: list[tuple[Path, str]] = []
        for path in paths:
            records = find_records(path) if path.exists() else []
            if path.is_file() and not path.name.endswith(RECORD_SUFFIX):
                raise ReportError(f"{path} is neither a drago run directory (no {CONFIG_FILE}) nor a record "
                                  f"(*{RECORD_SUFFIX})")
            if records and not (path / CONFIG_FILE).is_file():
                for record_path in records:
                    view = materialize(read_record(record_path), Path(scratch) / f"{len(found)}")
                    found.append((view, str(record_path)))
            else:
                found.extend((run_dir, str(run_dir)) for run_dir in find_run_dirs([path]))
        if not found:
            raise ReportError("no run directories given")
        yield found


def find_transfer_dirs(run_dir: Path) -> list[Path]:
    """The transfer runs a run directory holds (``RUN_DIR/transfer/*/config.yaml``), in sorted order."""
    return sorted(config.parent for config in (Path(run_dir) / TRANSFER_FOLDER).glob(f"*/{CONFIG_FILE}"))


@dataclass
class ReportedRun:
    """What a report needs from one run directory.

    Attributes:
        path: The run directory.
        cfg: Its resolved config.
        summary: ``summary.json``, or None before the first task finished.
        eval_rows: Rows of ``eval.csv`` (empty if absent).
        label: The method group the run is reported under (set once all runs are known).
        shown: How the report names the run: its directory, or the record it was read from.
    """

    path: Path
    cfg: Config
    summary: dict[str, Any] | None
    eval_rows: list[dict[str, str]]
    label: str = ""
    shown: str = ""

    def __post_init__(self) -> None:
        self.shown = self.shown or str(self.path)

    @property
    def method(self) -> str:
        return self.cfg.method.name

    @property
    def seed(self) -> int:
        return int(self.cfg.train.seed)

    @property
    def planned(self) -> list[str]:
        return list(self.cfg.env.tasks)

    @property
    def finished(self) -> dict[str, dict[str, Any]]:
        """Summary entries of the finished tasks, by task name."""
        return {task["name"]: task for task in (self.summary or {}).get("tasks", [])}

    @property
    def complete(self) -> bool:
        return len(self.finished) == len(self.planned)

    @property
    def is_transfer(self) -> bool:
        """A transfer run (a test task learned from another run's checkpoint), not a continual sequence."""
        return self.cfg.transfer.checkpoint is not None

    @property
    def case(self) -> tuple[str, int]:
        """A transfer's test case: (test task, as the catalogue names it, stage K). A grid transfer that ran
        the other reward than its task's own is a case of its own, e.g. ``("room1to2 (dense)", 2)``: its
        returns are on another scale and must not be averaged with the task's own."""
        task = self.cfg.transfer.case or self.cfg.env.tasks[0]
        own = GRID_TASKS.get(task)
        dense = self.cfg.env.dense_reward
        if own is not None and dense is not None and dense != own.dense:
            task = f"{task} ({'dense' if dense else 'sparse'})"
        return task, int(self.cfg.transfer.after or 0)


def _read_eval(path: Path, required: Sequence[str] = EVAL_COLUMNS) -> list[dict[str, str]]:
    file = path / EVAL_FILE
    if not file.exists():
        return []
    try:
        with file.open(newline="") as handle:
            reader = csv.DictReader(handle)
            rows = list(reader)
            columns = reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise ReportError(f"{file} is not a readable CSV file ({err})") from None
    missing = [c for c in required if c not in columns]
    if missing:
        raise ReportError(f"{file} lacks the column(s) {', '.join(missing)}")
    return rows


def read_run(path: str | Path, shown: str = "") -> ReportedRun:
    """Read one run directory (``shown``: how the report names it; default its path).

    Raises:
        ReportError: No ``config.yaml``, or an unreadable summary or eval file.
        drago.config.ConfigError: An invalid ``config.yaml``.
    """
    path = Path(path)
    try:
        cfg = read_run_config(path)
    except OSError as err:
        raise ReportError(f"{path / CONFIG_FILE} is not readable ({err.strerror or err})") from None
    # A domain without a known optimum (DeepMind Control) writes no fraction_of_optimal to eval.csv.
    required = EVAL_COLUMNS if is_domain(cfg.env.domain) and get_domain(cfg.env.domain).optimum else EVAL_COLUMNS[:2]
    return ReportedRun(path=path, cfg=cfg, summary=read_summary(path, ReportError),
                       eval_rows=_read_eval(path, required), shown=shown)


def as_number(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _method(run: ReportedRun) -> str:
    """The method a run is reported under: a transfer learned without the method's extras is its own."""
    return f"{run.method} (learner only)" if run.is_transfer and run.cfg.transfer.learner_only else run.method


#: A continual run's budget: runs of one method with different budgets are reported apart (a transfer's
#: budget is its case's, see :attr:`ReportedRun.case`).
BUDGET_SETTINGS = ("train.steps_per_task", "train.learner_steps_per_task", "train.reviewer_steps_per_task")


def _variant_settings(run: ReportedRun) -> dict[str, Any]:
    """The settings that make a run of a method another variant of it: the method's and the agent's own, and a
    continual run's budget; not those a run resolves for its machine (precision, compile), nor those it does not
    read or that change nothing for it (a clock of the reviewer's schedules for a method without a reviewer)."""
    flat = flat_settings(run.cfg)
    idle = idle_settings(run.cfg)
    return {key: value for key, value in flat.items()
            if (key.startswith(("method.", "agent.")) or (key in BUDGET_SETTINGS and not run.is_transfer))
            and key not in RESOLVED_AT_START and key != "agent.kind" and key not in idle}


def _setting_text(key: str, value: Any) -> str:
    shown = "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)
    return f"{key}={shown}"


def label_runs(runs: list[ReportedRun]) -> dict[str, list[ReportedRun]]:
    """Group runs by method, in order of first appearance, and split a method's runs wherever averaging them
    would mean nothing: by preset and by agent (``agent.kind``), and within one preset and agent by any
    setting of the method, the agent or the budget in which its runs differ, each shown as ``key=value``
    (``drago-no-rehearsal [method.reviewer.threshold_offset=3.0]``)."""
    variants: dict[str, set[tuple[str, str]]] = {}
    own = [_variant_settings(run) for run in runs]
    siblings: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for run, settings in zip(runs, own):
        variants.setdefault(_method(run), set()).add((run.cfg.preset, run.cfg.agent.kind))
        siblings.setdefault((_method(run), run.cfg.preset, run.cfg.agent.kind), []).append(settings)
    groups: dict[str, list[ReportedRun]] = {}
    for run, settings in zip(runs, own):
        method = _method(run)
        seen = variants[method]
        parts = [part for part, varies in ((run.cfg.preset, len({p for p, _ in seen}) > 1),
                                           (run.cfg.agent.kind, len({k for _, k in seen}) > 1)) if varies]
        others = siblings[(method, run.cfg.preset, run.cfg.agent.kind)]
        parts += [_setting_text(key, value) for key, value in settings.items()
                  if any(other.get(key) != value for other in others)]
        run.label = f"{method} [{', '.join(parts)}]" if parts else method
        groups.setdefault(run.label, []).append(run)
    return groups


def task_order(runs: Sequence[ReportedRun]) -> list[str]:
    order: list[str] = []
    for run in runs:
        order.extend(t for t in run.planned if t not in order)
    return order


Case = tuple[str, int]


def case_name(case: Case) -> str:
    return f"{case[0]} after {case[1]}"


def quantity_of(rows: Iterable[dict[str, str]]) -> tuple[str, str]:
    """The eval.csv column a curve shows and its axis label: the fraction of the optimum where the task
    has one (the grid), else the raw return (DeepMind Control, whose tasks have no known optimum)."""
    if any(math.isfinite(as_number(row.get("fraction_of_optimal"))) for row in rows):
        return "fraction_of_optimal", FRACTION_LABEL
    return "episode_reward", RETURN_LABEL
