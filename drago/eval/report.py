"""One page summarising any set of runs: tables with confidence intervals, curves, heatmaps, gaps.

:func:`build_report` reads run directories (several methods x several seeds, finished or not), groups
them by method (transfer runs, found in ``RUN_DIR/transfer/`` or given directly, apart: by test case
and method) and writes a self-contained HTML page (inline CSS, figures as data URIs, nothing
fetched) and a Markdown version with the figures as PNG files beside it. Both show the same tables,
built once as data here and only rendered twice.

Nothing is written into the run directories: coverage missing from a run (or out of date) is
computed in memory from its checkpoints, so a report can be built while experiments are running.
Whatever the runs do not (yet) provide is listed in a "Missing" section rather than left out silently.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import math
import os
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from drago.config import Config
from drago.envs.tasks import GRID_TASKS
from drago.eval.coverage import (
    ALL,
    COVERAGE_FILE,
    GRID_DOMAIN,
    ROOM_GROUPS,
    CoverageError,
    coverage_of_run,
    room_of,
    run_checkpoints,
)
from drago.eval.metrics import continual_metrics, cw_forward_transfer
from drago.eval.stats import summarize
from drago.train.rundir import CONFIG_FILE, SUMMARY_FILE, TRANSFER_FOLDER, RunDirError, read_run_config, read_summary
from drago.train.transfer import training_returns, transfer_summary

__all__ = ["ReportError", "build_report", "find_run_dirs", "find_transfer_dirs"]

REPORT_HTML = "report.html"
REPORT_MD = "report.md"
HEATMAP_PNG = "heatmap.png"
CURVES_PNG = "curves.png"
TRANSFER_PNG = "transfer-curves.png"
EVAL_FILE = "eval.csv"
EVAL_COLUMNS = ("task", "env_step", "fraction_of_optimal")
FRACTION_LABEL = "fraction of DP optimum"
RETURN_LABEL = "return"
DIGITS = 2
COVERAGE_COLUMNS = (*ROOM_GROUPS, ALL)


class ReportError(RunDirError):
    """A run or path a report cannot use; the message is one line (the CLI prints it, exit 2)."""


# ---------------------------------------------------------------------------------------------------
# reading runs
# ---------------------------------------------------------------------------------------------------
def find_run_dirs(paths: Iterable[str | Path]) -> list[Path]:
    """Run directories named by ``paths``: each path is a run (it has ``config.yaml``) or a folder
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


def find_transfer_dirs(run_dir: Path) -> list[Path]:
    """The transfer runs a run directory holds (``RUN_DIR/transfer/*/config.yaml``), in sorted order."""
    return sorted(config.parent for config in (Path(run_dir) / TRANSFER_FOLDER).glob(f"*/{CONFIG_FILE}"))


@dataclass
class Run:
    """What a report needs from one run directory.

    Attributes:
        path: The run directory.
        cfg: Its resolved config.
        summary: ``summary.json``, or None before the first task finished.
        eval_rows: Rows of ``eval.csv`` (empty if absent).
        label: The method group the run is reported under (set once all runs are known).
    """

    path: Path
    cfg: Config
    summary: dict[str, Any] | None
    eval_rows: list[dict[str, str]]
    label: str = ""

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
        """A transfer's test case: (test task, as the catalogue names it, stage K)."""
        return self.cfg.transfer.case or self.cfg.env.tasks[0], int(self.cfg.transfer.after or 0)


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


def read_run(path: str | Path) -> Run:
    """Read one run directory.

    Raises:
        ReportError: No ``config.yaml``, or an unreadable summary or eval file.
        drago.config.ConfigError: An invalid ``config.yaml``.
    """
    path = Path(path)
    try:
        cfg = read_run_config(path)
    except OSError as err:
        raise ReportError(f"{path / CONFIG_FILE} is not readable ({err.strerror or err})") from None
    # DeepMind Control tasks have no known optimum, so their eval.csv has no fraction_of_optimal.
    required = EVAL_COLUMNS if cfg.env.domain == GRID_DOMAIN else EVAL_COLUMNS[:2]
    return Run(path=path, cfg=cfg, summary=read_summary(path, ReportError), eval_rows=_read_eval(path, required))


def _number(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _method(run: Run) -> str:
    """The method a run is reported under: a transfer learned without the method's extras is its own."""
    return f"{run.method} (learner only)" if run.is_transfer and run.cfg.transfer.learner_only else run.method


def _label_runs(runs: list[Run]) -> dict[str, list[Run]]:
    """Group runs by method, in order of first appearance; a method run under several presets is
    split by preset, since their budgets differ and averaging them would mean nothing."""
    presets: dict[str, set[str]] = {}
    for run in runs:
        presets.setdefault(_method(run), set()).add(run.cfg.preset)
    groups: dict[str, list[Run]] = {}
    for run in runs:
        method = _method(run)
        run.label = method if len(presets[method]) == 1 else f"{method} [{run.cfg.preset}]"
        groups.setdefault(run.label, []).append(run)
    return groups


def _task_order(runs: Sequence[Run]) -> list[str]:
    order: list[str] = []
    for run in runs:
        order.extend(t for t in run.planned if t not in order)
    return order


def _task_room(name: str) -> str | None:
    """The room a task lives in (start and goal in the same room), else None (e.g. transfer tasks)."""
    task = GRID_TASKS.get(name)
    if task is None:
        return None
    start, goal = room_of(task.start), room_of(task.goal)
    return f"room{start}" if start is not None and start == goal else None


# ---------------------------------------------------------------------------------------------------
# report content: tables, figures and notes as data, rendered to HTML and Markdown below
# ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Table:
    key: str
    title: str
    caption: str
    columns: tuple[str, ...]
    rows: list[tuple[str, ...]]


@dataclass(frozen=True)
class Figure:
    key: str
    title: str
    caption: str
    png: bytes
    filename: str


@dataclass(frozen=True)
class Notes:
    key: str
    title: str
    caption: str
    items: list[str]


@dataclass
class _Findings:
    """What the report could not show, and how it got what it shows."""

    missing: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _fmt(values: Sequence[float]) -> tuple[str, int]:
    summary = summarize(values)
    return summary.format(DIGITS), summary.n


def _wall_time(seconds: Any) -> str:
    s = _number(seconds)
    if not math.isfinite(s):
        return "–"
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def _runs_table(groups: dict[str, list[Run]]) -> Table:
    rows = []
    for label, runs in groups.items():
        for run in runs:
            wall = (run.summary or {}).get("wall_time_s")
            rows.append((label, str(run.seed), run.cfg.preset, "yes" if run.complete else "no",
                         f"{len(run.finished)}/{len(run.planned)}", _wall_time(wall), str(run.path)))
    return Table("runs", "Runs", "One row per run directory; wall time is the sum over its finished tasks.",
                 ("method", "seed", "preset", "complete", "tasks done", "wall time", "run directory"), rows)


def _returns_table(groups: dict[str, list[Run]], tasks: list[str]) -> Table:
    rows = []
    for label, runs in groups.items():
        for task in tasks:
            entries = [run.finished[task] for run in runs if task in run.finished]
            if not entries:
                continue
            fraction, _ = _fmt([_number(e.get("fraction_of_optimal")) for e in entries])
            returns, _ = _fmt([_number(e.get("final_eval_return")) for e in entries])
            optima = [o for o in (_number(e.get("optimal_return")) for e in entries) if math.isfinite(o)]
            rows.append((label, task, str(len(entries)), fraction, returns, f"{optima[0]:.1f}" if optima else "–"))
    return Table("returns", "Final return per task",
                 "Evaluation return at the end of each task, and as a fraction of the DP-optimal return of "
                 "that task where one is known (the grid; not DeepMind Control): mean ± sample std [95% "
                 "bootstrap CI of the mean] over seeds; a single seed shows its value alone. Seeds counts only "
                 "runs that finished the task.",
                 ("method", "task", "seeds", "fraction of optimum", "return", "DP optimum"), rows)


def _task_curve(run: Run, task: str) -> tuple[dict[int, float], float]:
    """A finished task's evaluation curve (task env step -> value) and the best value its scale allows:
    1 for the fraction of the DP optimum (grid), the most a DeepMind Control episode can earn for raw
    return (reward at most 1 per control step)."""
    if task not in run.finished:
        return {}, math.nan
    rows = [r for r in run.eval_rows if r["task"] == task]
    key, _ = _quantity(rows)
    ceiling = 1.0 if key == "fraction_of_optimal" else float(run.cfg.env.episode_length * run.cfg.env.action_repeat)
    curve = {int(_number(r["env_step"])): _number(r[key]) for r in rows}
    return {x: y for x, y in curve.items() if math.isfinite(y)}, ceiling


def _forward_transfer_table(groups: dict[str, list[Run]], tasks: list[str], findings: _Findings) -> list[Table]:
    """Continual World forward transfer of every method against the `scratch` runs, from training curves."""
    reference = next((label for label, runs in groups.items() if runs and runs[0].method == "scratch"), None)
    others = [label for label in groups if label != reference]
    if not others:
        return []
    if reference is None:
        findings.missing.append("forward transfer: it needs `scratch` runs as the single-task reference "
                                "(Continual World); none were given")
        return []
    ref: dict[str, dict[int, float]] = {}
    for task in tasks:
        curves = [c for c in (_task_curve(run, task)[0] for run in groups[reference]) if c]
        steps = set.intersection(*(set(c) for c in curves)) if curves else set()
        ref[task] = {x: sum(c[x] for c in curves) / len(curves) for x in steps}
    rows = []
    for label in others:
        per_run: list[dict[str, float]] = []
        for run in groups[label]:
            transfer: dict[str, float] = {}
            for task in tasks:
                curve, ceiling = _task_curve(run, task)
                steps = sorted(set(curve) & set(ref[task]))
                if len(steps) < 2:
                    continue
                try:
                    transfer[task] = cw_forward_transfer([curve[x] for x in steps], [ref[task][x] for x in steps],
                                                         ceiling)
                except ValueError as err:
                    findings.notes.append(f"{run.path}: no forward transfer on {task} ({err})")
            if transfer:
                per_run.append(transfer)
        if per_run:
            means = [sum(t.values()) / len(t) for t in per_run]
            cells = [_fmt([t[task] for t in per_run if task in t])[0] if any(task in t for t in per_run) else "–"
                     for task in tasks]
            rows.append((label, str(len(per_run)), _fmt(means)[0], *cells))
    if not rows:
        return []
    return [Table("forward-transfer", "Forward transfer (Continual World)",
                  "FT = (AUC − AUC_ref) / (max − AUC_ref) per task (Wołczyk et al. 2021, §3), where AUC is the "
                  "time-average of the method's evaluation curve during its training on the task (trapezoid rule "
                  "over the evaluations both curves share), AUC_ref the same for `scratch` (a fresh world model per "
                  "task: the single-task reference, mean over its seeds), and max the scale's best value (1 for "
                  "the fraction of the DP optimum; the episode's control steps for DeepMind Control's raw return). "
                  "Positive: earlier tasks made this one faster to learn. 'mean' averages a run's tasks; mean ± "
                  "std [95% CI] over seeds.",
                  ("method", "seeds", "mean", *tasks), rows)]


def _coverage(run: Run, findings: _Findings) -> list[dict[str, Any]]:
    """The run's coverage rows: its coverage.csv when it matches its checkpoints, else computed."""
    if run.cfg.env.domain != GRID_DOMAIN:
        return []  # its retention matrix comes from held-out sets instead
    try:
        _, checkpoints = run_checkpoints(run.path)
    except CoverageError:
        return []  # no finished task: reported with the incomplete runs
    stages = {c.stage for c in checkpoints}
    file = run.path / COVERAGE_FILE
    if file.is_file():
        try:
            with file.open(newline="") as handle:
                rows = [dict(r, stage=int(r["stage"]), accuracy=_number(r["accuracy"]), score=_number(r["score"]))
                        for r in csv.DictReader(handle)]
            newest = max(c.path.stat().st_mtime for c in checkpoints)
            if {r["stage"] for r in rows} == stages and file.stat().st_mtime >= newest:
                return rows
            why = "its coverage.csv is older than or does not match its checkpoints"
        except (OSError, UnicodeDecodeError, csv.Error, KeyError, ValueError, TypeError):
            why = "its coverage.csv is unreadable"
    else:
        why = "it has no coverage.csv"
    findings.notes.append(f"{run.path}: coverage computed from the checkpoints ({why}); nothing was written")
    return coverage_of_run(run.path)


def _accuracy(rows: list[dict[str, Any]]) -> dict[tuple[int, str], float]:
    return {(int(r["stage"]), r["room"]): float(r["accuracy"]) for r in rows}


def _coverage_table(groups: dict[str, list[Run]], coverage: dict[Path, list[dict[str, Any]]]) -> Table:
    rows = []
    for label, runs in groups.items():
        by_run = [(_accuracy(coverage[run.path]), run) for run in runs if coverage.get(run.path)]
        stages = sorted({stage for acc, _ in by_run for stage, _ in acc})
        for stage in stages:
            reached = [(acc, run) for acc, run in by_run if (stage, ALL) in acc]
            task = reached[0][1].planned[stage - 1]
            cells = [_fmt([acc[(stage, room)] for acc, _ in reached])[0] for room in COVERAGE_COLUMNS]
            rows.append((label, f"{stage}: {task}", str(len(reached)), *cells))
    return Table("coverage", "World-model coverage",
                 "Exact-match accuracy of the world model after each stage: the share of the grid's "
                 "transitions (cell × heading × action) in each room whose predicted next state decodes "
                 "to the true one; 'all' includes the five centre openings. Mean ± std [95% CI] over seeds.",
                 ("method", "after stage", "seeds", *COVERAGE_COLUMNS), rows)


def _coverage_matrix(run: Run, rows: list[dict[str, Any]], findings: _Findings) -> list[list[float]]:
    """R[i][j] = coverage accuracy in the room of task j after stage i + 1, over the stages the run finished."""
    acc = _accuracy(rows)
    if not acc:
        return []
    rooms = [_task_room(task) for task in run.planned]
    if None in rooms:
        findings.missing.append(f"{run.path}: continual metrics need one room per task; "
                                f"{', '.join(t for t, r in zip(run.planned, rooms) if r is None)} has none")
        return []
    stages = 0
    while (stages + 1, ALL) in acc:
        stages += 1
    if stages == 0:
        findings.missing.append(f"{run.path}: no world model after task 1, so no continual metrics")
    return [[acc[(i + 1, room)] for room in rooms] for i in range(stages)]


def _retention_score_matrix(rows: list[dict[str, Any]]) -> list[list[float]]:
    """R[i][j] = held-out prediction score of task j's set after stage i + 1, over the largest T for which
    every stage i < T has a score on every set j < T (a missing set shortens T)."""
    score = {(int(r["stage"]), int(r["task_stage"])): float(r["score"]) for r in rows}
    stages = 0
    while all((i, j) in score for i in range(1, stages + 2) for j in range(1, stages + 2)):
        stages += 1
    return [[score[(i + 1, j + 1)] for j in range(stages)] for i in range(stages)]


def _metrics_table(groups: dict[str, list[Run]], matrices: dict[Path, list[list[float]]], table_id: str,
                   title: str, what: str) -> Table:
    """GEM ACC/BWT and Continual World forgetting of each run's matrix R, grouped by its stage count."""
    rows = []
    for label, runs in groups.items():
        by_stages: dict[int, list[dict[str, float]]] = {}
        for run in runs:
            R = matrices.get(run.path) or []
            if R:
                by_stages.setdefault(len(R), []).append(continual_metrics(R))
        for stages in sorted(by_stages, reverse=True):
            metrics = by_stages[stages]
            cells = [_fmt([m[key] for m in metrics])[0] for key in ("acc", "bwt", "forgetting")]
            rows.append((label, str(stages), str(len(metrics)), *cells))
    return Table(table_id, title,
                 f"R[i, j] = {what} after stage i, over the T stages a run finished. ACC (GEM) = mean over j of "
                 "R[T-1, j], equal to Continual World's average performance; BWT (GEM) = mean over j < T-1 of "
                 "R[T-1, j] − R[j, j], negative when the model forgets; forgetting (Continual World) = −BWT. "
                 "Runs are grouped by T, since values over different T do not compare; with T = 1 there is "
                 "nothing to forget (–).",
                 ("method", "stages T", "seeds", "ACC", "BWT", "forgetting"), rows)


def _retention_rows(run: Run, findings: _Findings) -> list[dict[str, Any]]:
    """A DeepMind Control run's retention rows from its held-out sets on disk (none is recorded here)."""
    from drago.eval.heldout import HeldoutError, heldout_checkpoints, heldout_path, retention_matrix

    if run.cfg.env.domain == GRID_DOMAIN:
        return []
    try:
        _, checkpoints = heldout_checkpoints(run.path)
    except HeldoutError:
        return []  # no finished task: reported with the incomplete runs
    missing = [c.task for c in checkpoints if not heldout_path(run.path, c.stage, c.task).is_file()]
    if missing:
        why = ("it was trained with train.heldout_episodes=0" if run.cfg.train.heldout_episodes == 0
               else f"`drago eval heldout {run.path}` records them from the checkpoints")
        findings.missing.append(f"{run.path}: no held-out set for {', '.join(missing)}, so the retention matrix "
                                f"lacks {'that column' if len(missing) == 1 else 'those columns'} ({why})")
    return retention_matrix(run.path) if len(missing) < len(checkpoints) else []


def _retention_tables(groups: dict[str, list[Run]], rows: dict[Path, list[dict[str, Any]]]) -> list[Table]:
    """The retention matrix of DeepMind Control runs (method x stage x held-out set), score and error."""
    if not any(rows.values()):
        return []
    tasks: list[str] = []
    for row in sorted((r for run_rows in rows.values() for r in run_rows), key=lambda r: r["task_stage"]):
        if row["task"] not in tasks:
            tasks.append(row["task"])
    score_rows, error_rows = [], []
    for label, runs in groups.items():
        cells: dict[tuple[int, str], dict[str, list[tuple[float, float]]]] = {}
        seeds: dict[tuple[int, str], set[Path]] = {}
        for run in runs:
            for r in rows[run.path]:
                key = (int(r["stage"]), r["stage_task"])
                cells.setdefault(key, {}).setdefault(r["task"], []).append((r["score"], r["error"]))
                seeds.setdefault(key, set()).add(run.path)
        for key in sorted(cells):
            stage = f"{key[0]}: {key[1]}"
            values = [cells[key].get(task, []) for task in tasks]
            score_rows.append((label, stage, str(len(seeds[key])), *(_fmt([v[0] for v in vs])[0] for vs in values)))
            error_rows.append((label, stage, str(len(seeds[key])),
                               *(summarize([v[1] for v in vs]).format(4) for vs in values)))
    columns = ("method", "after stage", "seeds", *tasks)
    what = ("the world model saved after each stage (rows) on the held-out transitions of each task (columns), "
            "recorded at the end of that task by its final learner in eval mode and never trained on")
    return [Table("retention", "World-model retention (held-out transitions)",
                  f"Prediction score −log(MSE + ε), higher is better, of {what}. Mean ± std [95% CI] over seeds.",
                  columns, score_rows),
            Table("retention-error", "World-model prediction error (held-out transitions)",
                  f"Mean squared one-step prediction error per state dimension (the training consistency error) of "
                  f"{what}. Mean ± std [95% CI] over seeds.", columns, error_rows)]


@dataclass(frozen=True)
class _Panel:
    """One panel of a learning-curve figure: per method, the values over seeds at each x."""

    title: str
    xlabel: str
    ylabel: str
    series: dict[str, dict[int, list[float]]]


def _quantity(rows: Iterable[dict[str, str]]) -> tuple[str, str]:
    """The eval.csv column a curve shows and its axis label: the fraction of the optimum where the task
    has one (the grid), else the raw return (DeepMind Control, whose tasks have no known optimum)."""
    if any(math.isfinite(_number(row.get("fraction_of_optimal"))) for row in rows):
        return "fraction_of_optimal", FRACTION_LABEL
    return "episode_reward", RETURN_LABEL


def _panel(title: str, xlabel: str, x_key: str, runs: dict[str, list[list[dict[str, str]]]]) -> _Panel:
    """A panel of ``runs`` (per method label, the eval rows each of its runs shows here) against ``x_key``."""
    y_key, ylabel = _quantity(row for per_run in runs.values() for rows in per_run for row in rows)
    series: dict[str, dict[int, list[float]]] = {}
    for label, per_run in runs.items():
        for rows in per_run:
            for row in rows:
                x, y = _number(row.get(x_key)), _number(row.get(y_key))
                if math.isfinite(x) and math.isfinite(y):
                    series.setdefault(label, {}).setdefault(int(x), []).append(y)
    return _Panel(title, xlabel, ylabel, series)


def _reviewer_steps(rows: Iterable[dict[str, str]]) -> bool:
    """Whether some evaluation counts env steps beyond the learner's (a reviewer's)."""
    return any(_number(row.get("learner_env_step")) < _number(row.get("env_step")) for row in rows)


def _panels_png(grid: list[list[_Panel]], colours: dict[str, str]) -> bytes | None:
    """Learning curves: rows x columns of panels, one line per method (mean over seeds) with its 95%
    bootstrap CI band where more than one seed has a value; empty panels are left blank."""
    if not any(panel.series for row in grid for panel in row):
        return None
    from matplotlib.figure import Figure as MplFigure

    n_rows, n_cols = len(grid), len(grid[0])
    same = all(panel.ylabel == FRACTION_LABEL for row in grid for panel in row)
    fig = MplFigure(figsize=(0.6 + 3.0 * n_cols, 0.4 + 2.8 * n_rows), layout="constrained")
    axes = fig.subplots(n_rows, n_cols, squeeze=False, sharey="all" if same else "col")
    for i, row in enumerate(grid):
        for j, panel in enumerate(row):
            ax = axes[i][j]
            for label, colour in colours.items():
                points = panel.series.get(label)
                if not points:
                    continue
                steps = sorted(points)
                stats = [summarize(points[s]) for s in steps]
                ax.plot(steps, [s.mean for s in stats], color=colour, label=label, marker=".")
                if any(s.n > 1 for s in stats):
                    ax.fill_between(steps, [s.ci_low for s in stats], [s.ci_high for s in stats],
                                    color=colour, alpha=0.2, linewidth=0)
            if i == 0:
                ax.set_title(panel.title, fontsize=10)
            ax.set_xlabel(panel.xlabel, fontsize=9)
            if j == 0 or not same:
                ax.set_ylabel(panel.ylabel, fontsize=9)
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=8)
    legend: dict[str, Any] = {}  # a method may be missing from some panels: one entry each, in order
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    fig.legend(list(legend.values()), list(legend), loc="outside right upper", fontsize=9, frameon=False)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=80)
    return buffer.getvalue()


def _curves_png(groups: dict[str, list[Run]], tasks: list[str], colours: dict[str, str]) -> bytes | None:
    """Return vs env steps, one panel per task; a second row against learner env steps only when a
    reviewer spent env steps of its own in some run."""
    by_task = {task: {label: [[r for r in run.eval_rows if r["task"] == task] for run in runs]
                      for label, runs in groups.items()} for task in tasks}
    shown = [t for t in tasks if any(rows for per_run in by_task[t].values() for rows in per_run)]
    if not shown:
        return None
    rows = [r for runs in groups.values() for run in runs for r in run.eval_rows]
    if _reviewer_steps(rows):
        grid = [[_panel(t, "learner env steps in the task", "learner_env_step", by_task[t]) for t in shown],
                [_panel(t, "total env steps in the task", "env_step", by_task[t]) for t in shown]]
    else:
        grid = [[_panel(t, "env steps in the task", "env_step", by_task[t]) for t in shown]]
    return _panels_png(grid, colours)


def _heatmap(groups: dict[str, list[Run]]) -> bytes | None:
    from drago.eval.heatmap import StageMaps, heatmap_png, run_cell_scores

    panels: dict[str, dict[int, StageMaps]] = {}
    for label, runs in groups.items():
        for run in runs:
            if run.cfg.env.domain != GRID_DOMAIN:
                continue
            try:
                maps = run_cell_scores(run.path)
            except CoverageError:
                continue  # no finished task: reported with the incomplete runs
            for checkpoint, cells in maps:
                entry = panels.setdefault(label, {}).setdefault(checkpoint.stage, StageMaps(checkpoint.task, []))
                entry.maps.append(cells)
    return heatmap_png(panels) if panels else None


def _gaps(groups: dict[str, list[Run]], tasks: list[str], findings: _Findings) -> None:
    """Incomplete runs, missing checkpoints and files, uneven seeds and unreached tasks."""
    for runs in groups.values():
        for run in runs:
            where = f"{run.path} ({run.label}, seed {run.seed})"
            if run.summary is None:
                findings.missing.append(f"{where}: no {SUMMARY_FILE}, no task finished yet")
            elif not run.complete:
                left = [t for t in run.planned if t not in run.finished]
                findings.missing.append(f"{where}: incomplete, {len(run.finished)} of {len(run.planned)} tasks "
                                        f"finished; not reached: {', '.join(left)}")
            for name, entry in run.finished.items():
                checkpoint = entry.get("checkpoint")
                if checkpoint and not (run.path / checkpoint).is_file():
                    findings.missing.append(f"{where}: the checkpoint of {name} ({checkpoint}) is missing, so that "
                                            f"stage has no coverage or heatmap")
            if run.finished and not run.eval_rows:
                findings.missing.append(f"{where}: no {EVAL_FILE}, so no learning curve")
    if not groups:
        return
    most = max(len(runs) for runs in groups.values())
    leader = next(label for label, runs in groups.items() if len(runs) == most)
    for label, runs in groups.items():
        seeds = sorted(run.seed for run in runs)
        if len(runs) < most:
            spread = "; one seed has no spread or confidence interval" if len(runs) == 1 else ""
            findings.missing.append(f"{label}: {len(runs)} seed(s) ({', '.join(map(str, seeds))}) against "
                                    f"{most} for {leader}{spread}")
        repeated = sorted({s for s in seeds if seeds.count(s) > 1})
        if repeated:
            findings.missing.append(f"{label}: seed(s) {', '.join(map(str, repeated))} appear in more than one "
                                    f"run, so those runs are not independent samples")
        unplanned = [t for t in tasks if not any(t in run.planned for run in runs)]
        if unplanned:
            findings.missing.append(f"{label}: {', '.join(unplanned)} not in its runs' task sequence")
        short: dict[int, list[str]] = {}
        for task in tasks:
            reached = sum(task in run.finished for run in runs)
            if task not in unplanned and reached < len(runs):
                short.setdefault(reached, []).append(task)
        for reached, names in short.items():
            findings.missing.append(f"{label}: {', '.join(names)} finished by {reached} of {len(runs)} runs")


# ---------------------------------------------------------------------------------------------------
# transfers (paper §4.4): test tasks learned from a run's stage-K world model
# ---------------------------------------------------------------------------------------------------
Case = tuple[str, int]

_FEW_SHOT = (
    ("equal_episodes", "transfer-episodes", "Transfer: few-shot score at equal learner episodes",
     "Evaluation return on each test case (a test task learned from the world model a run of the method saved "
     "after stage K, paper §4.4) after the same number of learner episodes (the transfer's few-shot "
     "episodes, 20 by default; the paper's reading), as a fraction of the task's DP optimum where it has "
     "one (grid) and as raw return: mean ± std [95% bootstrap CI of the mean] over seeds; a single seed "
     "shows its value alone. Seeds counts the transfers that have reached the score."),
    ("equal_env_steps", "transfer-env-steps", "Transfer: few-shot score at equal env steps",
     "The same score read at the last evaluation whose total env steps (learner plus reviewer) stay within "
     "what a learner alone spends in the few-shot episodes, so a method whose reviewer collects env steps "
     "of its own (DRAGO) is read after fewer learner episodes; without a reviewer both readings coincide. "
     "Mean ± std [95% CI] over seeds."),
)


def _case_name(case: Case) -> str:
    return f"{case[0]} after {case[1]}"


def _transfer_block(run: Run) -> dict[str, Any] | None:
    """A transfer's few-shot scores: its summary's once it has finished, else computed in memory from
    its eval.csv (the scores it has reached so far; nothing is written)."""
    block = (run.summary or {}).get("transfer") if run.complete else None
    if isinstance(block, dict) and isinstance(block.get("few_shot"), dict):
        return block
    try:
        return transfer_summary(run.cfg, run.path, [])
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, ValueError, TypeError):
        return None  # an unreadable eval.csv: read_run has reported it already


def _distinct(values: Iterable[Any], digits: int = 0) -> str:
    """The distinct values of a column over seeds, joined, so that one differing value stands out."""
    shown = [f"{n:.{digits}f}" for n in (_number(v) for v in values) if math.isfinite(n)]
    return ", ".join(dict.fromkeys(shown)) or "–"


def _by_case(tgroups: dict[str, list[Run]], cases: list[Case]) -> Iterator[tuple[Case, str, list[Run]]]:
    """(case, method label, that method's transfers of the case) for every pair that has any."""
    for case in cases:
        for label, runs in tgroups.items():
            mine = [run for run in runs if run.case == case]
            if mine:
                yield case, label, mine


def _transfer_tables(tgroups: dict[str, list[Run]], cases: list[Case],
                     blocks: dict[Path, dict[str, Any] | None]) -> list[Table]:
    tables = []
    for which, key, title, caption in _FEW_SHOT:
        rows = []
        for case, label, mine in _by_case(tgroups, cases):
            points = [p for p in ((blocks[run.path] or {}).get("few_shot", {}).get(which) for run in mine) if p]
            fraction, _ = _fmt([_number(p.get("fraction_of_optimal")) for p in points])
            returns, _ = _fmt([_number(p.get("return")) for p in points])
            rows.append((_case_name(case), label, str(len(points)), _distinct(p.get("episode") for p in points),
                         _distinct(p.get("total_env_steps") for p in points), fraction, returns,
                         _distinct(((blocks[run.path] or {}).get("optimal_return") for run in mine), 1)))
        tables.append(Table(key, title, caption, ("case", "method", "seeds", "learner episodes", "total env steps",
                                                  "fraction of optimum", "return", "optimum"), rows))
    return tables


def _training_table(tgroups: dict[str, list[Run]], cases: list[Case]) -> Table:
    """The learners' own episode returns over the few-shot episodes (:func:`training_returns`)."""
    rows = []
    for case, label, mine in _by_case(tgroups, cases):
        done = [t for t in (training_returns(run.cfg, run.path) for run in mine) if t]
        mean_return, _ = _fmt([t["mean_return"] for t in done])
        positive, _ = _fmt([t["positive_episodes"] for t in done])
        rows.append((_case_name(case), label, str(len(done)), _distinct(t["episodes"] for t in done),
                     mean_return, positive))
    return Table("transfer-training", "Transfer: the learner's return while it learns",
                 "The learner's own exploring episodes during the few-shot episodes (train.csv, not evaluations): "
                 "the mean return per episode, and how many episodes had a positive return. On a sparse-reward "
                 "grid task a positive return means the goal was reached, which the learner must see before its "
                 "planner can head there; an evaluation return of 0 with no such episode says the goal was never "
                 "found. Mean ± std [95% CI] over the seeds that have played every few-shot episode.",
                 ("case", "method", "seeds", "learner episodes", "mean episode return",
                  "episodes with a positive return"), rows)


def _source_run(transfer: Run) -> Path:
    """The run directory whose stage checkpoint a transfer started from (``RUN_DIR/checkpoints/*.pt``)."""
    return (transfer.path / str(transfer.cfg.transfer.checkpoint)).resolve().parent.parent


def _relearning_matrix(run: Run, relearned: dict[tuple[str, int], float],
                       findings: _Findings) -> list[list[float]]:
    """R[i][j] = the few-shot score of relearning training task j from the world model after stage i + 1,
    over the largest T for which every (stage < T, task < T) cell has a score; a gap is reported."""
    relearned = {key: score for key, score in relearned.items() if key[0] in run.planned}  # not test tasks
    stages = 0
    while stages < len(run.planned) and all((run.planned[j], i) in relearned
                                            for i in range(1, stages + 2) for j in range(stages + 1)):
        stages += 1
    lacking = [f"{run.planned[j]} after {i}" for i in range(1, len(run.planned) + 1)
               for j in range(len(run.planned)) if (run.planned[j], i) not in relearned]
    # Relearning from one stage only (the paper's walker table: the final model) is no attempt at a matrix.
    if len({after for _, after in relearned}) > 1 and stages < len(run.finished) and lacking:
        findings.missing.append(f"{run.path}: its relearning matrix stops at T = {stages}; it lacks "
                                f"{', '.join(lacking[:4])}{' ...' if len(lacking) > 4 else ''} "
                                f"(`drago transfer {run.path} --task TASK --after K`)")
    return [[relearned[(run.planned[j], i + 1)] for j in range(stages)] for i in range(stages)]


def _relearning_metrics(groups: dict[str, list[Run]], transfers: list[Run],
                        blocks: dict[Path, dict[str, Any] | None], findings: _Findings) -> list[Table]:
    """Continual-learning metrics of the return matrix: each training task relearned after each stage."""
    relearned: dict[Path, dict[tuple[str, int], float]] = {}
    for transfer in transfers:
        task, after = transfer.case
        point = (blocks[transfer.path] or {}).get("few_shot", {}).get("equal_episodes")
        if not point:
            continue  # not reached yet; test tasks never match a training task in _relearning_matrix
        fraction = _number(point.get("fraction_of_optimal"))
        relearned.setdefault(_source_run(transfer), {})[(task, after)] = (
            fraction if math.isfinite(fraction) else _number(point.get("return")))
    matrices = {run.path: _relearning_matrix(run, relearned.get(run.path.resolve(), {}), findings)
                for runs in groups.values() for run in runs}
    if not any(matrices.values()):
        return []
    return [_metrics_table(groups, matrices, "relearning-metrics", "Continual-learning metrics (from relearning)",
                           "the few-shot score (fraction of the DP optimum on the grid, raw return on DeepMind "
                           "Control) of relearning training task j with fresh heads (`drago transfer RUN --task "
                           "TASK_j --after i+1`) from the world model saved")]


def _transfer_png(tgroups: dict[str, list[Run]], cases: list[Case], colours: dict[str, str]) -> bytes | None:
    """Per case (columns): return vs learner env steps (top) and vs total env steps (bottom)."""
    def runs_of(case: Case) -> dict[str, list[list[dict[str, str]]]]:
        return {label: [run.eval_rows for run in runs if run.case == case] for label, runs in tgroups.items()}

    grid = [[_panel(_case_name(case), "learner env steps", "learner_env_step", runs_of(case)) for case in cases],
            [_panel(_case_name(case), "total env steps (learner + reviewer)", "env_step", runs_of(case))
             for case in cases]]
    return _panels_png(grid, colours)


def _transfer_gaps(groups: dict[str, list[Run]], tgroups: dict[str, list[Run]], cases: list[Case],
                   blocks: dict[Path, dict[str, Any] | None], findings: _Findings) -> None:
    """Unfinished transfers, scores not reached, cases some method or seed lacks, uneven few-shot episodes."""
    for label, runs in tgroups.items():
        for run in runs:
            where = f"{run.path} ({label}, seed {run.seed}, {_case_name(run.case)})"
            block = blocks[run.path]
            if block is None:
                findings.missing.append(f"{where}: no few-shot scores (unreadable {EVAL_FILE})")
                continue
            parts = []
            if not run.complete:
                done = max((int(e) for e in (_number(r.get("episode")) for r in run.eval_rows) if math.isfinite(e)),
                           default=0)
                parts.append(f"unfinished, {done} of {block.get('episodes_planned')} learner episodes evaluated")
            absent = [what.replace("_", " ") for what in ("equal_episodes", "equal_env_steps")
                      if not block["few_shot"].get(what)]
            if absent:
                parts.append(f"no few-shot score at {' or '.join(absent)} yet")
            if parts:
                findings.missing.append(f"{where}: {'; '.join(parts)}")
    domains = {run.case: run.cfg.env.domain for runs in tgroups.values() for run in runs}

    def applies(run: Run, case: Case) -> bool:  # a sequence run that could have this transfer
        return run.cfg.env.domain == domains[case] and case[1] <= len(run.planned)

    for label in dict.fromkeys([*groups, *tgroups]):
        transfers, sequence = tgroups.get(label, []), groups.get(label, [])
        for case in cases:
            expected = {run.seed for run in transfers} | {run.seed for run in sequence if applies(run, case)}
            have = sorted(run.seed for run in transfers if run.case == case)
            lacking = sorted(expected - set(have))
            if lacking:
                findings.missing.append(f"{label}: no transfer {_case_name(case)} for seed(s) "
                                        f"{', '.join(map(str, lacking))}")
            repeated = sorted({s for s in have if have.count(s) > 1})
            if repeated:
                findings.missing.append(f"{label}: seed(s) {', '.join(map(str, repeated))} of transfer "
                                        f"{_case_name(case)} appear in more than one run, so those runs are not "
                                        f"independent samples")
    for case in cases:
        episodes = {label: _distinct((blocks[run.path] or {}).get("few_shot_episodes") for run in runs
                                     if run.case == case) for label, runs in tgroups.items()}
        episodes = {label: e for label, e in episodes.items() if e != "–"}
        if len(set(episodes.values())) > 1 or any("," in e for e in episodes.values()):
            findings.missing.append(f"{_case_name(case)}: few-shot scores read after different numbers of learner "
                                    f"episodes ({'; '.join(f'{k}: {v}' for k, v in episodes.items())}), so they "
                                    f"do not compare")


# ---------------------------------------------------------------------------------------------------
# rendering
# ---------------------------------------------------------------------------------------------------
Section = Table | Figure | Notes

_CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 24px auto;
       max-width: 1240px; padding: 0 16px; color: #1d1d1f; line-height: 1.4; }
h1 { font-size: 26px; margin-bottom: 4px; } h2 { font-size: 19px; margin-top: 30px;
     border-bottom: 1px solid #ddd; padding-bottom: 4px; }
p.meta, p.caption { color: #555; font-size: 13px; margin: 4px 0 10px; }
nav a { margin-right: 14px; font-size: 14px; }
table { border-collapse: collapse; font-size: 13px; margin: 6px 0 8px; }
th, td { border: 1px solid #d6d6d6; padding: 3px 8px; text-align: left; white-space: nowrap; }
th { background: #eef1f5; } tr:nth-child(even) td { background: #fafafa; }
td.path { font-family: ui-monospace, Menlo, monospace; font-size: 12px; }
img { max-width: 100%; height: auto; border: 1px solid #e3e3e3; }
ul.notes li { font-size: 13px; margin: 3px 0; }
"""

# Lets a headless browser (and its test) see that every figure decoded and drew.
_IMAGES_LOADED_JS = """
window.addEventListener("load", function () {
  var images = Array.prototype.slice.call(document.images);
  document.body.dataset.imagesTotal = images.length;
  document.body.dataset.imagesLoaded =
    images.filter(function (img) { return img.complete && img.naturalWidth > 0; }).length;
});
"""


def _html(title: str, meta: str, sections: list[Section]) -> str:
    e = html.escape
    parts = [f"<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>{e(title)}</title>",
             f"<style>{_CSS}</style>\n</head>\n<body>", f"<h1>{e(title)}</h1>", f"<p class=\"meta\">{e(meta)}</p>",
             "<nav>" + "".join(f"<a href=\"#{s.key}\">{e(s.title)}</a>" for s in sections) + "</nav>"]
    for section in sections:
        parts.append(f"<section id=\"{section.key}\">\n<h2>{e(section.title)}</h2>")
        parts.append(f"<p class=\"caption\">{e(section.caption)}</p>")
        if isinstance(section, Table) and not section.rows:
            parts.append("<p class=\"caption\"><em>No data in these runs yet.</em></p>")
        elif isinstance(section, Table):
            head = "".join(f"<th>{e(c)}</th>" for c in section.columns)
            body = "\n".join("<tr>" + "".join(
                f"<td class=\"path\">{e(v)}</td>" if c == "run directory" else f"<td>{e(v)}</td>"
                for c, v in zip(section.columns, row)) + "</tr>" for row in section.rows)
            parts.append(f"<table id=\"table-{section.key}\">\n<thead><tr>{head}</tr></thead>\n"
                         f"<tbody>\n{body}\n</tbody>\n</table>")
        elif isinstance(section, Figure):
            data = base64.b64encode(section.png).decode("ascii")
            parts.append(f"<img id=\"figure-{section.key}\" alt=\"{e(section.title)}\" "
                         f"src=\"data:image/png;base64,{data}\">")
        else:
            parts.append("<ul class=\"notes\">\n" + "\n".join(f"<li>{e(i)}</li>" for i in section.items) + "\n</ul>")
        parts.append("</section>")
    parts.append(f"<script>{_IMAGES_LOADED_JS}</script>\n</body>\n</html>\n")
    return "\n".join(parts)


def _md_cell(value: str) -> str:
    return value.replace("|", "\\|")


def _markdown(title: str, meta: str, sections: list[Section]) -> str:
    lines = [f"# {title}", "", meta, ""]
    for section in sections:
        lines += [f"## {section.title}", "", section.caption, ""]
        if isinstance(section, Table) and not section.rows:
            lines.append("*No data in these runs yet.*")
        elif isinstance(section, Table):
            lines.append("| " + " | ".join(map(_md_cell, section.columns)) + " |")
            lines.append("|" + "|".join("---" for _ in section.columns) + "|")
            lines += ["| " + " | ".join(map(_md_cell, row)) + " |" for row in section.rows]
        elif isinstance(section, Figure):
            lines.append(f"![{section.title}]({section.filename})")
        else:
            lines += [f"- {item}" for item in section.items]
        lines.append("")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------------------------------
def build_report(run_dirs: Iterable[str | Path], out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``report.html`` (self-contained) and ``report.md`` (with PNG figures) for ``run_dirs``.

    Args:
        run_dirs: Run directories, or folders holding run directories (see :func:`find_run_dirs`).
            Any mix of methods and seeds, finished or not. The transfer runs each run holds
            (``RUN_DIR/transfer/*``) are reported too; a transfer run given directly is one of them,
            never a continual run of its method.
        out_dir: Output folder, created if needed; nothing is written anywhere else.

    Returns:
        ``(html_path, md_path)``.

    Raises:
        ReportError: A path without runs, or an unreadable run file (one-line message).
        drago.config.ConfigError: An invalid ``config.yaml``.
        drago.train.checkpoint.CheckpointError: A corrupt checkpoint.
    """
    given = [read_run(path) for path in find_run_dirs(run_dirs)]
    runs = [run for run in given if not run.is_transfer]
    transfers = [run for run in given if run.is_transfer]
    findings = _Findings()
    seen = {run.path.resolve() for run in given}
    for run in runs:
        for path in find_transfer_dirs(run.path):
            if path.resolve() in seen:
                continue
            seen.add(path.resolve())
            found = read_run(path)
            if found.is_transfer:
                transfers.append(found)
            else:
                findings.missing.append(f"{path}: not a transfer run (no transfer.checkpoint in its "
                                        f"{CONFIG_FILE}); left out")
    groups = _label_runs(runs)
    found_groups = _label_runs(transfers)
    tgroups = {label: found_groups[label] for label in dict.fromkeys([*groups, *found_groups]) if label in found_groups}
    colours = {label: f"C{i % 10}" for i, label in enumerate(dict.fromkeys([*groups, *tgroups]))}
    tasks = _task_order(runs)
    coverage = {run.path: _coverage(run, findings) for run in runs}

    sections: list[Section] = [_runs_table(groups), _returns_table(groups, tasks)]
    curves = _curves_png(groups, tasks, colours)
    if curves is not None:
        sections.append(Figure("curves", "Learning curves", "Evaluation return during each task, as a fraction of "
                               "the DP optimum (grid) or raw return (DeepMind Control, no known optimum), against "
                               "the task's env steps (learner plus reviewer; when a reviewer spent any, the top "
                               "row is against the learner's env steps alone): the mean over seeds with its 95% "
                               "bootstrap CI as a band (no band for a single seed).", curves, CURVES_PNG))
    sections += _forward_transfer_table(groups, tasks, findings)
    if any(run.cfg.env.domain == GRID_DOMAIN for run in runs):
        matrices = {run.path: _coverage_matrix(run, coverage[run.path], findings) for run in runs}
        sections += [_coverage_table(groups, coverage),
                     _metrics_table(groups, matrices, "metrics", "Continual-learning metrics (from coverage)",
                                    "coverage accuracy in the room of task j")]
    retention = {run.path: _retention_rows(run, findings) for run in runs}  # DeepMind Control runs only
    if any(retention.values()):
        sections += _retention_tables(groups, retention)
        matrices = {path: _retention_score_matrix(rows) for path, rows in retention.items()}
        sections.append(_metrics_table(
            groups, matrices, "retention-metrics", "Continual-learning metrics (from held-out retention)",
            "the world model's prediction score −log(MSE + ε) on the held-out transitions of task j"))
    heatmap = _heatmap(groups)
    if heatmap is not None:
        sections.append(Figure("heatmap", "World-model prediction score", "Per-cell prediction score of the "
                               "world model after each stage (rows: methods, columns: stages), the mean of "
                               "−log(MSE + ε) over the cell's 4 headings × 3 actions, averaged over seeds; "
                               "light = well predicted, one colour scale for all panels, walls and blocks "
                               "grey. The stage's task start (○) and goal (★) are marked; a red × is a cell "
                               "with a non-finite prediction.", heatmap, HEATMAP_PNG))
    if transfers:
        cases = sorted({run.case for run in transfers})
        blocks = {run.path: _transfer_block(run) for run in transfers}
        sections += _transfer_tables(tgroups, cases, blocks)
        sections.append(_training_table(tgroups, cases))
        sections += _relearning_metrics(groups, transfers, blocks, findings)
        transfer_curves = _transfer_png(tgroups, cases, colours)
        if transfer_curves is not None:
            sections.append(Figure("transfer-curves", "Transfer learning curves", "Evaluation return on each test "
                                   "case (columns) as a fraction of the DP optimum (grid) or raw return (DeepMind "
                                   "Control), against the learner's env steps (top) and the total env steps, "
                                   "learner plus reviewer (bottom): the mean over seeds with its 95% bootstrap CI "
                                   "as a band (no band for a single seed).", transfer_curves, TRANSFER_PNG))
        _transfer_gaps(groups, tgroups, cases, blocks, findings)
    _gaps(groups, tasks, findings)
    sections.append(Notes("missing", "Missing", "What these runs do not (yet) provide.",
                          findings.missing or ["Nothing: every run finished every task of its sequence, "
                                               "and every method has the same number of seeds."]))
    if findings.notes:
        sections.append(Notes("notes", "Notes", "How the numbers above were obtained.", findings.notes))

    seeds = ", ".join(f"{label}: {len(r)} run{'s' if len(r) != 1 else ''}" for label, r in groups.items())
    meta = f"Generated {datetime.now().strftime('%Y-%m-%d %H:%M')} from {len(runs)} run directories ({seeds or 'none'})"
    meta += f" and {len(transfers)} transfer run{'s' * (len(transfers) != 1)}." if transfers else "."
    title = "DRAGO report"
    out = Path(out_dir)
    html_path, md_path = out / REPORT_HTML, out / REPORT_MD
    try:
        out.mkdir(parents=True, exist_ok=True)
        for figure_file in (CURVES_PNG, HEATMAP_PNG, TRANSFER_PNG):
            (out / figure_file).unlink(missing_ok=True)  # a figure from an earlier report must not linger
        for section in sections:
            if isinstance(section, Figure):
                (out / section.filename).write_bytes(section.png)
        html_path.write_text(_html(title, meta, sections), encoding="utf-8")
        md_path.write_text(_markdown(title, meta, sections), encoding="utf-8")
    except OSError as err:
        raise ReportError(f"cannot write the report into {out} ({err.strerror or err})") from None
    return html_path, md_path
