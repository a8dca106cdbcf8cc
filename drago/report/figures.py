"""The report's figures: learning curves, transfer curves and the prediction-score heatmap (PNG bytes)."""

from __future__ import annotations

import io
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from drago.envs import exact_world
from drago.eval.coverage import (
    CoverageError,
)
from drago.eval.stats import summarize
from drago.report.runs import FRACTION_LABEL, Case, ReportedRun, as_number, case_name, quantity_of

HEATMAP_PNG = "heatmap.png"
CURVES_PNG = "curves.png"
TRANSFER_PNG = "transfer-curves.png"


@dataclass(frozen=True)
class Panel:
    """One panel of a learning-curve figure: per method, the values over seeds at each x."""

    title: str
    xlabel: str
    ylabel: str
    series: dict[str, dict[int, list[float]]]


def _panel(title: str, xlabel: str, x_key: str, runs: dict[str, list[list[dict[str, str]]]]) -> Panel:
    """A panel of ``runs`` (per method label, the eval rows each of its runs shows here) against ``x_key``."""
    y_key, ylabel = quantity_of(row for per_run in runs.values() for rows in per_run for row in rows)
    series: dict[str, dict[int, list[float]]] = {}
    for label, per_run in runs.items():
        for rows in per_run:
            for row in rows:
                x, y = as_number(row.get(x_key)), as_number(row.get(y_key))
                if math.isfinite(x) and math.isfinite(y):
                    series.setdefault(label, {}).setdefault(int(x), []).append(y)
    return Panel(title, xlabel, ylabel, series)


def _reviewer_steps(rows: Iterable[dict[str, str]]) -> bool:
    """Whether some evaluation counts env steps beyond the learner's (a reviewer's)."""
    return any(as_number(row.get("learner_env_step")) < as_number(row.get("env_step")) for row in rows)


def panels_png(grid: list[list[Panel]], colours: dict[str, str], rows_differ: bool = False) -> bytes | None:
    """Learning curves: rows x columns of panels, one line per method (mean over seeds) with its 95%
    bootstrap CI band where more than one seed has a value; empty panels are left blank. ``rows_differ``:
    each row shows a quantity of its own, so panels share the y axis along rows instead of columns."""
    if not any(panel.series for row in grid for panel in row):
        return None
    from matplotlib.figure import Figure as MplFigure

    n_rows, n_cols = len(grid), len(grid[0])
    same = not rows_differ and all(panel.ylabel == FRACTION_LABEL for row in grid for panel in row)
    fig = MplFigure(figsize=(0.6 + 3.0 * n_cols, 0.4 + 2.8 * n_rows), layout="constrained")
    axes = fig.subplots(n_rows, n_cols, squeeze=False, sharey="all" if same else ("row" if rows_differ else "col"))
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
            if j == 0 or not (same or rows_differ):
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


def curves_png(groups: dict[str, list[ReportedRun]], tasks: list[str], colours: dict[str, str]) -> bytes | None:
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
    return panels_png(grid, colours)


def heatmap_figure(groups: dict[str, list[ReportedRun]]) -> bytes | None:
    from drago.report.heatmap import StageMaps, heatmap_png, run_cell_scores

    panels: dict[str, dict[int, StageMaps]] = {}
    for label, runs in groups.items():
        for run in runs:
            if exact_world(run.cfg.env.domain) is None:
                continue
            try:
                maps = run_cell_scores(run.path)
            except CoverageError:
                continue  # no finished task: reported with the incomplete runs
            for checkpoint, cells in maps:
                entry = panels.setdefault(label, {}).setdefault(checkpoint.stage, StageMaps(checkpoint.task, []))
                entry.maps.append(cells)
    return heatmap_png(panels) if panels else None


def transfer_png(tgroups: dict[str, list[ReportedRun]], cases: list[Case], colours: dict[str, str]) -> bytes | None:
    """Per case (columns): return vs learner env steps (top) and vs total env steps (bottom)."""
    def runs_of(case: Case) -> dict[str, list[list[dict[str, str]]]]:
        return {label: [run.eval_rows for run in runs if run.case == case] for label, runs in tgroups.items()}

    grid = [[_panel(case_name(case), "learner env steps", "learner_env_step", runs_of(case)) for case in cases],
            [_panel(case_name(case), "total env steps (learner + reviewer)", "env_step", runs_of(case))
             for case in cases]]
    return panels_png(grid, colours)
