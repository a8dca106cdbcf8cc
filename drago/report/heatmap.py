"""Prediction-score heatmaps of grid world models: the paper's forgetting figure (paper §4.1).

Each panel is the 27x27 map coloured by the per-cell prediction score of one world model (the mean of
``-log(MSE + eps)`` over the cell's 4 headings x 3 actions, :func:`~drago.eval.coverage.cell_scores`),
rows are methods and columns the stages of the sequence (the model after task k). As in the paper,
light means the model predicts that part of the world well. Every panel shares one colour scale, so
a pale region in one panel means the same score as in any other.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from drago.envs.fourrooms import SIZE, is_traversable
from drago.envs.tasks import GRID_TASKS
from drago.eval.coverage import cell_scores, grid_coverage, grid_world_models, run_checkpoints
from drago.eval.unit import read_cells
from drago.training.rundir import RunCheckpoint

__all__ = ["StageMaps", "heatmap_png", "run_cell_scores"]

# Light = well predicted, as in the paper's figure; walls and blocks are drawn in a neutral grey.
COLORMAP = "viridis"
WALL_COLOUR = "#b8b8b8"
SCORE_LABEL = "prediction score  −log(MSE + ε)\nmean over 4 headings × 3 actions"


class StageMaps(NamedTuple):
    """The per-cell score maps of one method after one stage, one map per seed.

    Attributes:
        task: Name of the task learned in this stage (its start and goal are marked).
        maps: (SIZE, SIZE) arrays from :func:`~drago.eval.coverage.cell_scores`, one per seed.
    """

    task: str
    maps: Sequence[np.ndarray]


def run_cell_scores(run_dir: str | Path, device: str = "cpu") -> list[tuple[RunCheckpoint, np.ndarray]]:
    """Per-cell score map of the world model after each finished task of a grid run (a record view's are
    read from its file).

    Raises:
        CoverageError: Not a grid run, or no task finished yet (see :func:`run_checkpoints`).
        drago.training.checkpoint.CheckpointError: A corrupt or mismatched checkpoint.
    """
    recorded = read_cells(run_dir)
    if recorded is not None:
        return recorded
    _, checkpoints = run_checkpoints(run_dir)
    return [(checkpoint, cell_scores(grid_coverage(predictor).score)) for checkpoint, predictor in
            grid_world_models(checkpoints, device, "heatmaps are defined for the grid only (domains on an exact world)")]


def _wall_mask() -> np.ndarray:
    return np.array([[not is_traversable((x, y)) for x in range(SIZE)] for y in range(SIZE)])


def heatmap_png(panels: Mapping[str, Mapping[int, StageMaps]], dpi: int = 80, label: str = SCORE_LABEL,
                empty: str = "no world model", stage_title: str = "after task") -> bytes:
    """The heatmap figure as PNG bytes: one row per method, one column per stage.

    Args:
        panels: ``{method: {stage: StageMaps}}``, methods in row order, stages counted from 1. A
            stage without a model for a method (not reached, or beyond its sequence) is an empty
            panel saying so. Several maps (seeds) in a panel are averaged cell by cell.
        dpi: Resolution of the PNG.
        label: What the colour scale measures (default: the world models' prediction score).
        empty: What an empty panel says.
        stage_title: What a panel's title calls its stage, before the stage's number.

    Returns:
        PNG bytes. A cell whose averaged score is not finite (a diverged prediction) is drawn at the
        bottom of the scale and crossed in red, so it can neither look good nor vanish.

    Raises:
        ValueError: If there is nothing to draw.
    """
    import matplotlib
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    stages = sorted({stage for per_method in panels.values() for stage in per_method})
    if not stages:
        raise ValueError("heatmap_png needs at least one panel")
    columns = range(1, max(stages) + 1)
    walls = _wall_mask()
    means: dict[tuple[str, int], np.ndarray] = {
        (method, stage): np.mean(np.stack([np.asarray(m, dtype=np.float64) for m in entry.maps]), axis=0)
        for method, per_method in panels.items() for stage, entry in per_method.items() if len(entry.maps)}
    finite = np.concatenate([m[~walls & np.isfinite(m)] for m in means.values()] or [np.empty(0)])
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if high <= low:
        high = low + 1.0
    norm = Normalize(vmin=low, vmax=high)
    cmap = matplotlib.colormaps[COLORMAP].with_extremes(bad=WALL_COLOUR)

    methods = list(panels)
    fig = Figure(figsize=(1.0 + 2.3 * len(columns), 0.7 + 2.35 * len(methods)), layout="constrained")
    axes = fig.subplots(len(methods), len(columns), squeeze=False)
    for row, method in enumerate(methods):
        for col, stage in enumerate(columns):
            ax = axes[row][col]
            ax.set_xticks([])
            ax.set_yticks([])
            if col == 0:
                ax.set_ylabel(method, fontsize=11, fontweight="bold")
            entry = panels[method].get(stage)
            if entry is None or (method, stage) not in means:
                ax.set_facecolor("#f4f4f4")
                ax.set_title(f"{stage_title} {stage}", fontsize=9)
                ax.text(0.5, 0.5, empty, ha="center", va="center", transform=ax.transAxes,
                        fontsize=9, color="#777777")
                continue
            values = means[(method, stage)]
            diverged = ~walls & ~np.isfinite(values)
            shown = np.ma.masked_array(np.where(diverged, low, values), mask=walls)
            ax.imshow(shown, cmap=cmap, norm=norm, interpolation="nearest", origin="upper")
            if diverged.any():
                ys, xs = np.nonzero(diverged)
                ax.scatter(xs, ys, marker="x", c="red", s=6, linewidths=0.8)
            task = GRID_TASKS.get(entry.task)
            if task is not None:
                ax.scatter(*task.start, marker="o", s=40, c="white", edgecolors="black", linewidths=1.0)
                ax.scatter(*task.goal, marker="*", s=110, c="white", edgecolors="black", linewidths=0.8)
            seeds = len(entry.maps)
            ax.set_title(f"{stage_title} {stage}: {entry.task}\n({seeds} seed{'s' if seeds != 1 else ''})",
                         fontsize=9)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=axes, shrink=0.8, label=label)
    handles = [Line2D([], [], marker="o", ls="", mfc="white", mec="black", label="start of the stage's task"),
               Line2D([], [], marker="*", ls="", ms=11, mfc="white", mec="black", label="goal"),
               Line2D([], [], marker="s", ls="", ms=9, mfc=WALL_COLOUR, mec=WALL_COLOUR, label="wall / block")]
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=9, frameon=False)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()
