"""Retention for continuous states: world models scored on every task's held-out transitions.

The grid's coverage enumerates every transition (:mod:`drago.eval.coverage`); a continuous state space
cannot be enumerated. Instead, at the end of each task of a DeepMind Control run the trainer records a
held-out set: ``train.heldout_episodes`` episodes of that task's final learner in eval mode, on an env
instance and seeds of their own, saved to ``RUN_DIR/heldout/task<k>_<name>.npz`` (``obs``, ``action``,
``next_obs``, ``reward``). They are evaluation data only: no buffer ever sees them, and recording them
moves none of the training's random streams.

:func:`retention_matrix` evaluates the world model saved after every stage i on every task j's set:

* ``error``: the mean over transitions of the squared prediction error averaged over state dimensions,
  the same quantity as the training consistency error (one step, the planner's prediction);
* ``score``: the mean over transitions of ``-log(error_t + eps)``, the code's prediction score (higher
  is better; the same as the grid's coverage score).

Row i of the matrix is what the world model after stage i still (or already) predicts: a model that
forgets task 1 while learning task 3 has a growing error on task 1's set.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from drago.agent.losses import LOG_EPS
from drago.config import Config
from drago.envs import exact_world
from drago.eval.predictor import load_world_model
from drago.training.heldout_sets import HeldoutSet, load_heldout, record_heldout
from drago.training.rundir import (HELDOUT_FOLDER, RunCheckpoint, RunDirError, heldout_path, run_checkpoints,
                                  write_rows_csv)

__all__ = ["CSV_COLUMNS", "HELDOUT_FOLDER", "RETENTION_FILE", "HeldoutError", "HeldoutSet", "format_table",
           "heldout_checkpoints", "heldout_path", "load_heldout", "record_heldout",
           "retention_matrix", "transition_errors", "write_retention_csv"]

RETENTION_FILE = "retention.csv"
# stage / stage_task: the world model (saved after that stage); task / task_stage: whose held-out set.
CSV_COLUMNS: tuple[str, ...] = ("run", "method", "seed", "stage", "stage_task", "task_stage", "task", "error",
                                "score", "n")


class HeldoutError(RunDirError):
    """A run the retention matrix cannot evaluate; the message is one line (the CLI prints it, exit 2)."""


def heldout_checkpoints(run_dir: str | Path) -> tuple[Config, list[RunCheckpoint]]:
    """The run's config and its finished tasks' checkpoints, in task order (files only: cheap).

    Raises:
        HeldoutError: not a run directory, a grid run, or no task finished yet.
        drago.config.ConfigError: the run's ``config.yaml`` is invalid.
    """
    return run_checkpoints(run_dir, HeldoutError, lambda cfg: (
        "held-out retention is for continuous states: use `drago eval coverage` for the grid"
        if exact_world(cfg.env.domain) is not None else None))


def transition_errors(predicted: np.ndarray, next_obs: np.ndarray) -> np.ndarray:
    """Per-transition squared error averaged over state dimensions (float64)."""
    diff = np.asarray(predicted, dtype=np.float64) - np.asarray(next_obs, dtype=np.float64)
    return np.square(diff).mean(axis=-1)


def retention_matrix(run_dir: str | Path, device: str = "cpu", record_missing: bool = False) -> list[dict[str, Any]]:
    """Every finished stage's world model on every held-out set of the run.

    Args:
        run_dir: a DeepMind Control run directory.
        device: torch device for the predictions (and any recording).
        record_missing: record (and save) the held-out set of a finished task that has none, from its
            checkpoint (a run trained before held-out sets existed, or one that crashed in between).

    Returns:
        Rows with the keys of :data:`CSV_COLUMNS`, one per (stage, held-out set), stages in task order
        and sets in task order.

    Raises:
        HeldoutError: see :func:`heldout_checkpoints`, or no held-out set at all.
        drago.training.checkpoint.CheckpointError: a corrupt or mismatched checkpoint.
    """
    run_dir = Path(run_dir)
    cfg, checkpoints = heldout_checkpoints(run_dir)
    sets: dict[int, tuple[str, HeldoutSet]] = {}
    for c in checkpoints:
        path = heldout_path(run_dir, c.stage, c.task)
        if not path.is_file() and record_missing and cfg.train.heldout_episodes > 0:
            record_heldout(c.path, path, device)
        if path.is_file():
            sets[c.stage] = (c.task, load_heldout(path))
    if not sets:
        why = ("it was trained with train.heldout_episodes=0" if cfg.train.heldout_episodes == 0
               else f"run `drago eval heldout {run_dir}` to record them from its checkpoints")
        raise HeldoutError(f"{run_dir} has no held-out sets in {HELDOUT_FOLDER}/ ({why})")
    rows = []
    for c in checkpoints:
        model = load_world_model(c.path, device=device)
        for stage, (task, data) in sets.items():
            errors = transition_errors(model.predict(data.obs, data.action), data.next_obs)
            n = int(errors.shape[0])
            rows.append({"run": str(run_dir), "method": cfg.method.name, "seed": cfg.train.seed, "stage": c.stage,
                         "stage_task": c.task, "task_stage": stage, "task": task,
                         "error": float(errors.mean()) if n else math.nan,
                         "score": float(np.mean(-np.log(errors + LOG_EPS))) if n else math.nan, "n": n})
    return rows


def write_retention_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """Write retention rows (columns :data:`CSV_COLUMNS`) to ``path``, replacing it atomically."""
    return write_rows_csv(rows, CSV_COLUMNS, path)


def format_table(rows: list[dict[str, Any]]) -> list[str]:
    """Text tables, one per run: rows are stages, columns held-out sets, cells the prediction score."""
    lines: list[str] = []
    runs: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        runs.setdefault(row["run"], []).append(row)
    for run, run_rows in runs.items():
        tasks = list(dict.fromkeys(f"{r['task_stage']}: {r['task']}" for r in run_rows))
        stages = list(dict.fromkeys(f"{r['stage']}: {r['stage_task']}" for r in run_rows))
        cell = {(f"{r['stage']}: {r['stage_task']}", f"{r['task_stage']}: {r['task']}"): r["score"] for r in run_rows}
        width = max(len(s) for s in [*stages, "after stage"])
        widths = [max(len(t), 8) for t in tasks]
        lines.append(run)
        lines.append(f"  {'after stage':<{width}}" + "".join(f"  {t:>{w}}" for t, w in zip(tasks, widths)))
        for stage in stages:
            cells = "".join(f"  {cell[(stage, t)]:>{w}.3f}" if (stage, t) in cell else f"  {'-':>{w}}"
                            for t, w in zip(tasks, widths))
            lines.append(f"  {stage:<{width}}{cells}")
    return lines
