"""World-model coverage on the four-rooms grid: how much of the world a carried model still predicts.

Every (traversable cell, heading, action) of the fixed map is one transition (561 x 4 x 3 = 6,732).
The true next state comes from stepping a real :class:`~drago.envs.fourrooms.FourRoomsEnv`; the
prediction comes from the world model exactly as the planner sees it. Two measures per room:

* exact-match accuracy: the prediction decoded to the nearest cell and heading
  (:func:`~drago.envs.fourrooms.decode_observation`) equals the true next state;
* mean prediction score, ``-log(mean_dims (predicted - true)^2 + eps)`` (paper §4.1), the same quantity
  as the training code's prediction score, higher is better.

Evaluated for the world model after each task of a run, these show retention: a model that forgot
room 1 while learning room 4 loses accuracy in room 1.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np

from drago.agent.losses import LOG_EPS
from drago.config import Config
from drago.envs.fourrooms import (
    ROOM_BOUNDS,
    SIZE,
    FourRoomsEnv,
    traversable_cells,
)
from drago.envs import exact_world
from drago.envs.tasks import GRID_TASKS, get_grid_task
from drago.training.rundir import RunCheckpoint, RunDirError, write_rows_csv
from drago.training.rundir import run_checkpoints as _run_checkpoints

__all__ = [
    "GROUPS",
    "CSV_COLUMNS",
    "CoverageError",
    "CoverageResult",
    "GridTransitions",
    "Predictor",
    "RunCheckpoint",
    "cell_scores",
    "coverage_of_run",
    "decode_batch",
    "format_table",
    "grid_coverage",
    "grid_transitions",
    "room_group",
    "room_of",
    "run_checkpoints",
    "write_coverage_csv",
]

# Report groups, in order: the four rooms, the five-cell opening at the centre of the wall cross
# (it belongs to no room), and every transition together.
ROOM_GROUPS: tuple[str, ...] = tuple(f"room{k}" for k in sorted(ROOM_BOUNDS))
CORRIDOR = "corridor"
ALL = "all"
GROUPS: tuple[str, ...] = (*ROOM_GROUPS, CORRIDOR, ALL)
CSV_COLUMNS: tuple[str, ...] = ("run", "method", "seed", "stage", "stage_task", "room", "accuracy", "score", "n")
COVERAGE_FILE = "coverage.csv"


class CoverageError(RunDirError):
    """A run that coverage cannot evaluate; the message is one line (the CLI prints it, exit 2)."""


class Predictor(Protocol):
    """Anything that maps (N, 3) observations and (N, 3) one-hot actions to (N, 3) predictions."""

    def predict(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray: ...


class GridTransitions(NamedTuple):
    """Every transition of the grid, row order: cell (``traversable_cells`` order), heading, action.

    Attributes:
        obs: (N, 3) float32 observations.
        actions: (N, 3) float32 one-hot actions.
        next_obs: (N, 3) float32 true next observations.
        cells: (N, 2) int64 cells ``(x, y)``.
        headings: (N,) int64 headings in {0, 1, 2, 3}.
        action_idx: (N,) int64 actions: 0 left, 1 right, 2 forward.
    """

    obs: np.ndarray
    actions: np.ndarray
    next_obs: np.ndarray
    cells: np.ndarray
    headings: np.ndarray
    action_idx: np.ndarray


@dataclass(frozen=True)
class CoverageResult:
    """Coverage of one world model.

    Attributes:
        correct: (N,) bool, per transition of :func:`grid_transitions`: decoded prediction is exact.
        score: (N,) float64 per-transition prediction score ``-log(MSE + eps)``.
        predicted: (N, 3) float32 predictions, for pictures.
        rooms: Summary per group of :data:`GROUPS`: ``{"accuracy", "score", "n"}``.
    """

    correct: np.ndarray
    score: np.ndarray
    predicted: np.ndarray
    rooms: dict[str, dict[str, float | int]]


def room_of(cell: tuple[int, int]) -> int | None:
    """The room (1..4) of a cell, or None for a cell in no room.

    The only traversable cells in no room are the five openings of the wall cross at the centre,
    (13, 12), (12, 13), (13, 13), (14, 13) and (13, 14); :func:`grid_coverage` reports them as the
    separate ``"corridor"`` group (and within ``"all"``), never inside a room.
    """
    x, y = int(cell[0]), int(cell[1])
    for room, (x_lo, x_hi, y_lo, y_hi) in ROOM_BOUNDS.items():
        if x_lo <= x <= x_hi and y_lo <= y <= y_hi:
            return room
    return None


def task_room(name: str) -> str | None:
    """The room a task lives in (start and goal in the same room), else None (e.g. transfer tasks)."""
    task = GRID_TASKS.get(name)
    if task is None:
        return None
    start, goal = room_of(task.start), room_of(task.goal)
    return f"room{start}" if start is not None and start == goal else None


def room_group(cell: tuple[int, int]) -> str:
    """The report group of a cell: ``"room1"`` .. ``"room4"`` or ``"corridor"``."""
    room = room_of(cell)
    return CORRIDOR if room is None else f"room{room}"


@lru_cache(maxsize=1)
def _stepped_transitions() -> tuple[GridTransitions, np.ndarray, np.ndarray]:
    """All transitions plus the true next (cell, heading) as integers, read from the env's info."""
    # The task only fixes start and reward, neither of which affects where a step leads.
    env = FourRoomsEnv(get_grid_task("room1"))
    env.reset(seed=0)
    eye = np.eye(3, dtype=np.float32)
    obs, actions, next_obs, cells, headings, action_idx, next_cells, next_headings = ([] for _ in range(8))
    for cell in traversable_cells():
        for heading in range(4):
            for a in range(3):
                start = env.set_state(cell, heading)
                after, _, _, _, info = env.step(eye[a])
                obs.append(start)
                actions.append(eye[a])
                next_obs.append(after)
                cells.append(cell)
                headings.append(heading)
                action_idx.append(a)
                next_cells.append(info["pos"])
                next_headings.append(info["dir"])
    arrays = GridTransitions(
        obs=np.asarray(obs, dtype=np.float32), actions=np.asarray(actions, dtype=np.float32),
        next_obs=np.asarray(next_obs, dtype=np.float32), cells=np.asarray(cells, dtype=np.int64),
        headings=np.asarray(headings, dtype=np.int64), action_idx=np.asarray(action_idx, dtype=np.int64))
    truth_cells = np.asarray(next_cells, dtype=np.int64)
    truth_headings = np.asarray(next_headings, dtype=np.int64)
    # The arrays are shared by every caller through the cache, so nobody may change them in place.
    for array in (*arrays, truth_cells, truth_headings):
        array.setflags(write=False)
    return arrays, truth_cells, truth_headings


def grid_transitions() -> GridTransitions:
    """Every (traversable cell, heading, action) of the grid with its true next observation.

    The true next state is obtained by putting a real env in the state (``set_state``) and stepping
    it. The result is computed once and cached; its arrays are read-only.

    Returns:
        A :class:`GridTransitions` of 6,732 rows (561 cells x 4 headings x 3 actions), which also
        unpacks as ``(obs, actions, next_obs, cells, headings, action_idx)``.
    """
    return _stepped_transitions()[0]


@lru_cache(maxsize=1)
def transition_groups() -> np.ndarray:
    """The group of :data:`GROUPS` (a room or the corridor) of each row of :func:`grid_transitions`."""
    cells = grid_transitions().cells
    return np.asarray([room_group((x, y)) for x, y in cells])


def decode_batch(obs: np.ndarray) -> np.ndarray:
    """Vectorised :func:`~drago.envs.fourrooms.decode_observation`: (N, 3) -> (N, 3) int ``(x, y, dir)``.

    Non-finite rows decode to -1 in every column, so they never match a real state.
    """
    o = np.asarray(obs, dtype=np.float64).reshape(-1, 3)
    # The same arithmetic as decode_observation, in float64, so both decode a row identically.
    scaled = np.stack([(o[:, 0] + 1.0) * SIZE / 2.0, (o[:, 1] + 1.0) * SIZE / 2.0, (o[:, 2] + 1.0) * 2.0], axis=1)
    upper = np.array([SIZE - 1, SIZE - 1, 3], dtype=np.float64)
    decoded = np.clip(np.rint(scaled), 0.0, upper)
    finite = np.isfinite(o).all(axis=1)
    out = np.full(decoded.shape, -1, dtype=np.int64)
    out[finite] = decoded[finite].astype(np.int64)
    return out


def grid_coverage(predictor: Predictor) -> CoverageResult:
    """Exact-match accuracy and prediction score of a world model on every grid transition.

    Args:
        predictor: Anything with ``predict(obs, action)`` as :class:`drago.eval.predictor.WorldModelPredictor`.

    Returns:
        A :class:`CoverageResult` with per-transition arrays (rows of :func:`grid_transitions`) and
        the per-group summary for ``room1`` .. ``room4``, ``corridor`` (the five centre openings)
        and ``all``. A prediction with NaN never matches, and its NaN score makes its group's mean
        score NaN, so a diverged model cannot look good.

    Raises:
        ValueError: If the predictor returns an array of the wrong shape.
    """
    data, truth_cells, truth_headings = _stepped_transitions()
    predicted = np.asarray(predictor.predict(data.obs, data.actions), dtype=np.float32)
    if predicted.shape != data.next_obs.shape:
        raise ValueError(f"predictor returned shape {predicted.shape}, expected {data.next_obs.shape}")
    decoded = decode_batch(predicted)
    correct = ((decoded[:, :2] == truth_cells).all(axis=1) & (decoded[:, 2] == truth_headings))
    mse = ((predicted.astype(np.float64) - data.next_obs.astype(np.float64)) ** 2).mean(axis=1)
    score = -np.log(mse + LOG_EPS)
    groups = transition_groups()
    rooms: dict[str, dict[str, float | int]] = {}
    for group in GROUPS:
        mask = np.ones(len(groups), dtype=bool) if group == ALL else groups == group
        rooms[group] = {"accuracy": float(correct[mask].mean()), "score": float(score[mask].mean()),
                        "n": int(mask.sum())}
    return CoverageResult(correct=correct, score=score, predicted=predicted, rooms=rooms)


def run_checkpoints(run_dir: str | Path) -> tuple[Config, list[RunCheckpoint]]:
    """The run's config and its finished tasks' checkpoints, in task order (files only: cheap).

    Raises:
        CoverageError: Not a run directory, a domain other than the grid, or no task finished yet.
        drago.config.ConfigError: The run's ``config.yaml`` is invalid.
    """
    return _run_checkpoints(run_dir, CoverageError, lambda cfg: (
        f"coverage is defined for the grid only (domains on an exact world); {cfg.env.domain} is not one"
        if exact_world(cfg.env.domain) is None else None))


def grid_world_models(checkpoints: Iterable[RunCheckpoint], device: str, refusal: str,
                      error: type[RunDirError] = CoverageError) -> Iterator[tuple[RunCheckpoint, Any]]:
    """Each checkpoint with its world model as a numpy predictor, refusing one of another domain with
    ``error("PATH comes from domain 'X'; " + refusal)`` (checkpoints are checked as they are loaded)."""
    from drago.eval.predictor import load_world_model

    for checkpoint in checkpoints:
        predictor = load_world_model(checkpoint.path, device=device)
        if exact_world(predictor.domain) is None:
            raise error(f"{checkpoint.path} comes from domain '{predictor.domain}'; {refusal}")
        yield checkpoint, predictor


def coverage_of_run(run_dir: str | Path, device: str = "cpu") -> list[dict[str, Any]]:
    """Coverage of the world model after each finished task of a run.

    Args:
        run_dir: A run directory (with ``config.yaml`` and ``checkpoints/``).
        device: Torch device for the predictions.

    Returns:
        Rows with the keys of :data:`CSV_COLUMNS`, one per (stage, group), stages in task order and
        groups in :data:`GROUPS` order. ``stage`` is the task index + 1 after which the model was
        saved, ``stage_task`` that task's name, ``room`` the group.

    Raises:
        CoverageError: See :func:`run_checkpoints`.
        drago.training.checkpoint.CheckpointError: A corrupt or mismatched checkpoint.
    """
    cfg, checkpoints = run_checkpoints(run_dir)
    rows: list[dict[str, Any]] = []
    refusal = "coverage is defined for the grid only (domains on an exact world)"
    for checkpoint, predictor in grid_world_models(checkpoints, device, refusal):
        result = grid_coverage(predictor)
        for group, summary in result.rooms.items():
            rows.append({"run": str(run_dir), "method": cfg.method.name, "seed": cfg.train.seed,
                         "stage": checkpoint.stage, "stage_task": checkpoint.task, "room": group,
                         "accuracy": summary["accuracy"], "score": summary["score"], "n": summary["n"]})
    return rows


def write_coverage_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """Write coverage rows (columns :data:`CSV_COLUMNS`) to ``path``, replacing it atomically."""
    return write_rows_csv(rows, CSV_COLUMNS, path)


def format_table(rows: list[dict[str, Any]]) -> list[str]:
    """Compact text table: one line per (run, stage) with the accuracy of each group."""
    by_stage: dict[tuple[str, int], dict[str, Any]] = {}
    for row in rows:
        key = (row["run"], row["stage"])
        entry = by_stage.setdefault(key, {"task": row["stage_task"], "method": row["method"], "seed": row["seed"]})
        entry[row["room"]] = row["accuracy"]
    width = max([len("run")] + [len(run) for run, _ in by_stage])
    header = f"{'run':<{width}}  stage  {'after':<8}" + "".join(f"  {g:>8}" for g in GROUPS)
    lines = [header]
    for (run, stage), entry in by_stage.items():
        cells = "".join(f"  {entry[g]:>8.3f}" if g in entry else f"  {'-':>8}" for g in GROUPS)
        lines.append(f"{run:<{width}}  {stage:>5}  {entry['task']:<8}{cells}")
    return lines


def cell_scores(score: np.ndarray) -> np.ndarray:
    """Per-cell prediction score on the map: the mean over each cell's 4 headings x 3 actions (paper §4.1).

    Args:
        score: (N,) per-transition scores in the row order of :func:`grid_transitions`, e.g.
            :attr:`CoverageResult.score`.

    Returns:
        (SIZE, SIZE) float64 array indexed ``[y, x]`` (image order: row y, column x). Walls and blocks
        are NaN; so is a traversable cell with a non-finite prediction, since a mean over a diverged
        prediction is meaningless (use :func:`~drago.envs.fourrooms.is_traversable` to tell them apart).

    Raises:
        ValueError: If ``score`` does not have one entry per grid transition.
    """
    cells = grid_transitions().cells
    score = np.asarray(score, dtype=np.float64)
    if score.shape != (len(cells),):
        raise ValueError(f"score has shape {score.shape}, expected ({len(cells)},): one per grid transition")
    flat = cells[:, 1] * SIZE + cells[:, 0]
    total = np.zeros(SIZE * SIZE)
    count = np.zeros(SIZE * SIZE)
    np.add.at(total, flat, score)
    np.add.at(count, flat, 1.0)
    out = np.full(SIZE * SIZE, np.nan)
    seen = count > 0
    out[seen] = total[seen] / count[seen]
    return out.reshape(SIZE, SIZE)
