"""One page summarising any set of runs: tables with confidence intervals, curves, heatmaps, gaps.

:func:`build_report` reads run directories (several methods x several seeds, finished or not), groups
them by method and writes a self-contained HTML page (inline CSS, figures as data URIs, nothing
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
import json
import math
import os
from collections.abc import Iterable, Sequence
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
from drago.eval.metrics import continual_metrics
from drago.eval.stats import summarize
from drago.train.run import CONFIG_FILE, RunDirError, read_run_config

__all__ = ["ReportError", "build_report", "find_run_dirs"]

REPORT_HTML = "report.html"
REPORT_MD = "report.md"
HEATMAP_PNG = "heatmap.png"
CURVES_PNG = "curves.png"
SUMMARY_FILE = "summary.json"
EVAL_FILE = "eval.csv"
EVAL_COLUMNS = ("task", "env_step", "fraction_of_optimal")
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
    directory: what lies there (``transfer/`` runs) is another kind of experiment. Duplicates are dropped.

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


def _read_summary(path: Path) -> dict[str, Any] | None:
    file = path / SUMMARY_FILE
    if not file.exists():
        return None
    try:
        data = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ReportError(f"{file} is not readable JSON ({err})") from None
    if not isinstance(data, dict) or not isinstance(data.get("tasks"), list) or not all(
            isinstance(t, dict) and "name" in t for t in data["tasks"]):
        raise ReportError(f"{file} is not a drago run summary (no list of tasks with names)")
    return data


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
    return Run(path=path, cfg=cfg, summary=_read_summary(path), eval_rows=_read_eval(path, required))


def _number(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _label_runs(runs: list[Run]) -> dict[str, list[Run]]:
    """Group runs by method, in order of first appearance; a method run under several presets is
    split by preset, since their budgets differ and averaging them would mean nothing."""
    presets: dict[str, set[str]] = {}
    for run in runs:
        presets.setdefault(run.method, set()).add(run.cfg.preset)
    groups: dict[str, list[Run]] = {}
    for run in runs:
        run.label = run.method if len(presets[run.method]) == 1 else f"{run.method} [{run.cfg.preset}]"
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
                 "Evaluation return at the end of each task, as a fraction of the DP-optimal return of "
                 "that task: mean ± sample std [95% bootstrap CI of the mean] over seeds; a single seed "
                 "shows its value alone. Seeds counts only runs that finished the task.",
                 ("method", "task", "seeds", "fraction of optimum", "return", "DP optimum"), rows)


def _coverage(run: Run, findings: _Findings) -> list[dict[str, Any]]:
    """The run's coverage rows: its coverage.csv when it matches its checkpoints, else computed."""
    if run.cfg.env.domain != GRID_DOMAIN:
        findings.missing.append(f"{run.path}: a '{run.cfg.env.domain}' run; coverage and heatmaps are "
                                f"defined for the '{GRID_DOMAIN}' grid only")
        return []
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


def _metrics_table(groups: dict[str, list[Run]], coverage: dict[Path, list[dict[str, Any]]],
                   findings: _Findings) -> Table:
    rows = []
    for label, runs in groups.items():
        by_stages: dict[int, list[dict[str, float]]] = {}
        for run in runs:
            acc = _accuracy(coverage.get(run.path, []))
            if not acc:
                continue
            rooms = [_task_room(task) for task in run.planned]
            if None in rooms:
                findings.missing.append(f"{run.path}: continual metrics need one room per task; "
                                        f"{', '.join(t for t, r in zip(run.planned, rooms) if r is None)} has none")
                continue
            stages = 0
            while (stages + 1, ALL) in acc:
                stages += 1
            if stages == 0:
                findings.missing.append(f"{run.path}: no world model after task 1, so no continual metrics")
                continue
            R = [[acc[(i + 1, room)] for room in rooms] for i in range(stages)]
            by_stages.setdefault(stages, []).append(continual_metrics(R))
        for stages in sorted(by_stages, reverse=True):
            metrics = by_stages[stages]
            cells = [_fmt([m[key] for m in metrics])[0] for key in ("acc", "bwt", "forgetting")]
            rows.append((label, str(stages), str(len(metrics)), *cells))
    return Table("metrics", "Continual-learning metrics (from coverage)",
                 "R[i, j] = coverage accuracy in the room of task j after stage i, over the T stages a run "
                 "finished. ACC (GEM) = mean over j of R[T-1, j], equal to Continual World's average "
                 "performance; BWT (GEM) = mean over j < T-1 of R[T-1, j] − R[j, j], negative when the model "
                 "forgets; forgetting (Continual World) = −BWT. Runs are grouped by T, since values over "
                 "different T do not compare; with T = 1 there is nothing to forget (–).",
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


def _retention_tables(groups: dict[str, list[Run]], findings: _Findings) -> list[Table]:
    """The retention matrix of DeepMind Control runs (method x stage x held-out set), score and error."""
    rows = {run.path: _retention_rows(run, findings) for runs in groups.values() for run in runs}
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


def _curves_png(groups: dict[str, list[Run]], tasks: list[str]) -> bytes | None:
    """Fraction of optimum vs env step, one panel per task, one line per method with its 95% CI band."""
    series: dict[tuple[str, str], dict[int, list[float]]] = {}
    for label, runs in groups.items():
        for run in runs:
            for row in run.eval_rows:
                value = _number(row.get("fraction_of_optimal"))
                step = _number(row["env_step"])
                if math.isfinite(value) and math.isfinite(step):
                    series.setdefault((label, row["task"]), {}).setdefault(int(step), []).append(value)
    if not series:
        return None
    from matplotlib.figure import Figure as MplFigure

    shown = [t for t in tasks if any(task == t for _, task in series)]
    fig = MplFigure(figsize=(0.6 + 3.0 * len(shown), 3.2), layout="constrained")
    axes = fig.subplots(1, len(shown), squeeze=False, sharey=True)[0]
    colours = {label: f"C{i}" for i, label in enumerate(groups)}
    for ax, task in zip(axes, shown):
        for label in groups:
            points = series.get((label, task))
            if not points:
                continue
            steps = sorted(points)
            stats = [summarize(points[s]) for s in steps]
            ax.plot(steps, [s.mean for s in stats], color=colours[label], label=label, marker=".")
            if any(s.n > 1 for s in stats):
                ax.fill_between(steps, [s.ci_low for s in stats], [s.ci_high for s in stats],
                                color=colours[label], alpha=0.2, linewidth=0)
        ax.set_title(task, fontsize=10)
        ax.set_xlabel("env steps in the task", fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)
    axes[0].set_ylabel("fraction of DP optimum", fontsize=9)
    legend: dict[str, Any] = {}  # a method may be missing from some panels: one entry each, in order
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    fig.legend(list(legend.values()), list(legend), loc="outside right upper", fontsize=9, frameon=False)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=80)
    return buffer.getvalue()


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
            Any mix of methods and seeds, finished or not.
        out_dir: Output folder, created if needed; nothing is written anywhere else.

    Returns:
        ``(html_path, md_path)``.

    Raises:
        ReportError: A path without runs, or an unreadable run file (one-line message).
        drago.config.ConfigError: An invalid ``config.yaml``.
        drago.train.checkpoint.CheckpointError: A corrupt checkpoint.
    """
    runs = [read_run(path) for path in find_run_dirs(run_dirs)]
    groups = _label_runs(runs)
    tasks = _task_order(runs)
    findings = _Findings()
    coverage = {run.path: _coverage(run, findings) for run in runs}

    sections: list[Section] = [_runs_table(groups), _returns_table(groups, tasks)]
    curves = _curves_png(groups, tasks)
    if curves is not None:
        sections.append(Figure("curves", "Learning curves", "Evaluation return as a fraction of the DP optimum "
                               "during each task: the mean over seeds with its 95% bootstrap CI as a band "
                               "(no band for a single seed).", curves, CURVES_PNG))
    sections += [_coverage_table(groups, coverage), _metrics_table(groups, coverage, findings)]
    sections += _retention_tables(groups, findings)  # DeepMind Control runs only
    heatmap = _heatmap(groups)
    if heatmap is not None:
        sections.append(Figure("heatmap", "World-model prediction score", "Per-cell prediction score of the "
                               "world model after each stage (rows: methods, columns: stages), the mean of "
                               "−log(MSE + ε) over the cell's 4 headings × 3 actions, averaged over seeds; "
                               "light = well predicted, one colour scale for all panels, walls and blocks "
                               "grey. The stage's task start (○) and goal (★) are marked; a red × is a cell "
                               "with a non-finite prediction.", heatmap, HEATMAP_PNG))
    _gaps(groups, tasks, findings)
    sections.append(Notes("missing", "Missing", "What these runs do not (yet) provide.",
                          findings.missing or ["Nothing: every run finished every task of its sequence, "
                                               "and every method has the same number of seeds."]))
    if findings.notes:
        sections.append(Notes("notes", "Notes", "How the numbers above were obtained.", findings.notes))

    seeds = ", ".join(f"{label}: {len(r)} run{'s' if len(r) != 1 else ''}" for label, r in groups.items())
    meta = f"Generated {datetime.now().strftime('%Y-%m-%d %H:%M')} from {len(runs)} run directories ({seeds})."
    title = "DRAGO report"
    out = Path(out_dir)
    html_path, md_path = out / REPORT_HTML, out / REPORT_MD
    try:
        out.mkdir(parents=True, exist_ok=True)
        for figure_file in (CURVES_PNG, HEATMAP_PNG):
            (out / figure_file).unlink(missing_ok=True)  # a figure from an earlier report must not linger
        for section in sections:
            if isinstance(section, Figure):
                (out / section.filename).write_bytes(section.png)
        html_path.write_text(_html(title, meta, sections), encoding="utf-8")
        md_path.write_text(_markdown(title, meta, sections), encoding="utf-8")
    except OSError as err:
        raise ReportError(f"cannot write the report into {out} ({err.strerror or err})") from None
    return html_path, md_path
