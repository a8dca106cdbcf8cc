"""What each method stores and spends: the bytes a run carries across each task boundary, by kind, beside the
env steps, gradient steps and CPU time of each task (docs: Evaluation, "What each method stores and spends").

The bytes are read from the task checkpoint the next task starts from: the world model, and the method's
carried state (:meth:`~drago.continual.base.ContinualMethod.carry_state`) counted tensor by tensor
(``numel x element size``), grouped by what it is. Only ``replay`` carries raw transitions of earlier tasks;
DRAGO carries a generator (the VAE) and starts the next task with a frozen copy of the carried world model, made
from it (so it stores nothing more across the boundary, but holds a second model in memory during the task);
EWC carries a Fisher diagonal and an anchor copy of the world model's weights. The learner's own heads, which
a checkpoint also keeps for inspection, are not carried (the next task starts new heads) and not counted.

Steps come from the run's summary. Gradient steps are counted from ``train.csv``: every training iteration
past the seed phase runs ``train.updates_per_episode`` updates of each network whose losses that row logs
(the learner's, DRAGO's reviewer's, the VAE's).
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from drago.training.rundir import read_summary, write_rows_csv
from drago.training.rundir import run_checkpoints as _run_checkpoints

__all__ = ["COSTS_FILE", "COST_COLUMNS", "CARRIED_KINDS", "RAW_DATA_KINDS", "carried_bytes", "costs_of_run",
           "read_costs", "write_costs_csv"]

COSTS_FILE = "costs.csv"
#: What each key of a method's carried state is, by the name the method gives it.
CARRIED_KINDS = {"vae": "generator", "fisher": "fisher", "anchor": "anchor", "reservoir": "raw_transitions"}
#: Kinds that are data of earlier tasks as they were observed.
RAW_DATA_KINDS = ("raw_transitions",)
BYTE_KINDS = ("world_model", "generator", "fisher", "anchor", "raw_transitions", "other")
COST_COLUMNS = ("run", "method", "seed", "stage", "task", *(f"bytes_{kind}" for kind in BYTE_KINDS), "bytes_total",
                "raw_data", "learner_env_steps", "reviewer_env_steps", "learner_updates", "reviewer_updates",
                "vae_updates", "cpu_s")


def _tensor_bytes(value: Any) -> int:
    if isinstance(value, torch.Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, Mapping):
        return sum(_tensor_bytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(_tensor_bytes(v) for v in value)
    return 0  # numbers and flags: a few bytes of bookkeeping, not what a method stores


def carried_bytes(world_model: Mapping[str, Any], carried: Mapping[str, Any]) -> dict[str, int]:
    """Bytes by kind of what a task boundary carries: the world model's state dict and the method's state."""
    out = dict.fromkeys(BYTE_KINDS, 0)
    out["world_model"] = _tensor_bytes(world_model)
    for key, value in carried.items():
        out[CARRIED_KINDS.get(key, "other")] += _tensor_bytes(value)
    return out


def _updates(run_dir: Path, per_iteration: int) -> dict[str, dict[str, int]]:
    """Gradient updates per task and network, from the rows of ``train.csv`` that logged each one's loss."""
    counts: dict[str, dict[str, int]] = {}
    columns = {"learner": "learner_total_loss", "reviewer": "reviewer_total_loss", "vae": "vae_loss"}
    try:
        with (run_dir / "train.csv").open(newline="") as handle:
            for row in csv.DictReader(handle):
                mine = counts.setdefault(row["task"], dict.fromkeys(columns, 0))
                for network, column in columns.items():
                    if row.get(column) not in (None, ""):
                        mine[network] += per_iteration
    except OSError:
        pass
    return counts


def costs_of_run(run_dir: str | Path) -> list[dict[str, Any]]:
    """One row per finished task: what its checkpoint carries to the next task, and what the task spent.

    Raises:
        drago.training.rundir.RunDirError: not a run directory, or no finished task.
        drago.training.checkpoint.CheckpointError: a corrupt checkpoint.
    """
    from drago.training.checkpoint import load_checkpoint

    run_dir = Path(run_dir)
    cfg, checkpoints = _run_checkpoints(run_dir)
    summary = read_summary(run_dir) or {}
    spent = {t["name"]: t for t in summary.get("tasks", [])}
    updates = _updates(run_dir, cfg.updates_per_episode)
    rows = []
    for checkpoint in checkpoints:
        data = load_checkpoint(checkpoint.path, kind="task", domain=cfg.env.domain)
        sizes = carried_bytes(data["world_model"], data.get("method") or {})
        task = spent.get(checkpoint.task, {})
        learner = int(task.get("learner_steps", 0))
        counted = updates.get(checkpoint.task, {})
        rows.append({"run": f"{cfg.method.name}/seed{cfg.train.seed}", "method": cfg.method.name,
                     "seed": cfg.train.seed, "stage": checkpoint.stage, "task": checkpoint.task,
                     **{f"bytes_{kind}": sizes[kind] for kind in BYTE_KINDS}, "bytes_total": sum(sizes.values()),
                     "raw_data": any(sizes[kind] for kind in RAW_DATA_KINDS),
                     "learner_env_steps": learner,
                     "reviewer_env_steps": int(task.get("env_steps", learner)) - learner,
                     "learner_updates": counted.get("learner", 0), "reviewer_updates": counted.get("reviewer", 0),
                     "vae_updates": counted.get("vae", 0), "cpu_s": task.get("cpu_time_s")})
    return rows


def write_costs_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    return write_rows_csv(rows, COST_COLUMNS, path)


def read_costs(run_dir: str | Path) -> list[dict[str, Any]] | None:
    """A run's ``costs.csv`` rows, numbers as numbers, or None when it has none."""
    try:
        with (Path(run_dir) / COSTS_FILE).open(newline="") as handle:
            rows = list(csv.DictReader(handle))
    except OSError:
        return None
    numeric = [c for c in COST_COLUMNS if c not in ("run", "method", "task", "raw_data", "cpu_s")]
    return [dict(r, **{c: int(r[c]) for c in numeric}, raw_data=r["raw_data"] == "True",
                 cpu_s=float(r["cpu_s"]) if r["cpu_s"] else None) for r in rows]

