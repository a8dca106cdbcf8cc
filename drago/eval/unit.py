"""A study unit's evaluations: everything measured from a run's checkpoints, written as files into the run
directory so that its record carries them (docs: Command line, "Records: studies that outlive the machine").

A checkpoint lives only on the machine that trained it, so each evaluation is made once, right after the run
and its transfer cases, and read back from its file ever after (by the report, ``drago eval`` tables and the
API, from a run directory or a record alike). The list of evaluations is part of a unit's protocol: adding
one makes the units recorded without it due again.

Grid runs (a tabular domain with a known reward): world-model coverage per room (``coverage.csv``), the
zero-shot return matrix (``zero_shot.csv``), the per-cell prediction scores of the paper's forgetting
heatmap (``cells.json``), for the methods that pay a reviewer what it is paid (``reviewer_pay.json``), the
retention of each part of the agent and the swap test (``components.csv``, ``swap.csv``,
:mod:`drago.eval.components`). DeepMind Control runs: held-out retention (``retention.csv``). Every run:
what it carries across each task boundary and what each task spent (``costs.csv``, :mod:`drago.eval.costs`).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drago.config import Config
from drago.envs import get_domain
from drago.eval.coverage import (
    COVERAGE_FILE,
    cell_scores,
    coverage_of_run,
    grid_coverage,
    grid_world_models,
    run_checkpoints,
    task_room,
    transition_groups,
    write_coverage_csv,
)
from drago.eval.reviewer_pay import PAID, reviewer_pay_of_run
from drago.training.records import (
    RecordError,
    export_record,
    is_record_view,
    run_protocol,
    write_record,
)
from drago.training.rundir import (CONFIG_FILE, SUMMARY_FILE, TRANSFER_FOLDER, RunCheckpoint, atomic_write_text,
                                   read_run_config)

__all__ = ["CELLS_FILE", "EVALUATION_VERSIONS", "REVIEWER_PAY_FILE", "PaySummary", "evaluate_unit", "read_cells",
           "read_reviewer_pay", "record_unit", "unit_cpu_seconds", "unit_evaluations", "unit_protocol"]

CELLS_FILE = "cells.json"
REVIEWER_PAY_FILE = "reviewer_pay.json"


def _is_grid(cfg: Config) -> bool:
    domain = get_domain(cfg.env.domain)
    return bool(domain.tabular and domain.optimum is not None)


def unit_evaluations(cfg: Config) -> list[str]:
    """The names of the evaluations a unit of this run's domain makes from its checkpoints."""
    if _is_grid(cfg):
        # components reads the zero-shot rows: it comes after zero_shot
        return ["coverage", "zero_shot", "cells", "reviewer_pay", "components", "costs"]
    return ["retention", "costs"]


#: Evaluations whose measure changed after units were recorded with it, by version. The protocol names such
#: an evaluation ``NAME@VERSION``, so a unit recorded with an earlier version is due again; a study then
#: redoes only its record job (the evaluations are made again from the run's checkpoints), as long as the
#: run directory is still there. components@2: the swap test's refit is the mean of several refits;
#: components@3: each refit's learning rate decays over a longer budget, so that more refits settle.
EVALUATION_VERSIONS = {"components": 3}


def unit_protocol(run: Config, transfers: Mapping[str, Config]) -> dict[str, Any]:
    """A unit's protocol (:func:`~drago.training.records.run_protocol`) with this drago's evaluations."""
    evaluations = [f"{name}@{EVALUATION_VERSIONS[name]}" if name in EVALUATION_VERSIONS else name
                   for name in unit_evaluations(run)]
    return run_protocol(run, transfers, evaluations)


# ---- the evaluations -------------------------------------------------------------------------------
def _json_cells(cells: np.ndarray) -> list[list[float | None]]:
    return [[float(v) if math.isfinite(v) else None for v in row] for row in np.asarray(cells, dtype=np.float64)]


def _array_cells(rows: Sequence[Sequence[float | None]]) -> np.ndarray:
    return np.array([[math.nan if v is None else float(v) for v in row] for row in rows], dtype=np.float64)


def _cells(run_dir: Path) -> dict[str, Any]:
    _, checkpoints = run_checkpoints(run_dir)
    stages = [{"stage": checkpoint.stage, "task": checkpoint.task,
               "cells": _json_cells(cell_scores(grid_coverage(predictor).score))}
              for checkpoint, predictor in grid_world_models(checkpoints, "cpu", "heatmaps need the grid")]
    return {"stages": stages}


@dataclass(frozen=True)
class PaySummary:
    """What the reviewer is paid when the task after ``stage`` begins, as the report shows it.

    Attributes:
        stage, task, next_task, threshold: as in :class:`~drago.eval.reviewer_pay.StagePay`.
        old_rooms_paid: share of the transitions in the rooms of the tasks up to ``stage`` whose old-model
            term exceeds :data:`~drago.eval.reviewer_pay.PAID`.
        rooms: per room group, the mean old-model term, the share paid and the mean reward.
        reward_cells: (SIZE, SIZE) mean reward per cell (walls NaN).
    """

    stage: int
    task: str
    next_task: str
    threshold: float
    old_rooms_paid: float
    rooms: dict[str, dict[str, float]]
    reward_cells: np.ndarray


def _pay_summaries(run_dir: Path) -> list[PaySummary]:
    cfg = read_run_config(run_dir)
    groups = transition_groups()
    out = []
    for pay in reviewer_pay_of_run(run_dir):
        rooms = {task_room(task) for task in cfg.env.tasks[:pay.stage]} - {None}
        mask = np.isin(groups, sorted(rooms))
        paid = float((pay.old_term[mask] > PAID).mean()) if mask.any() else math.nan
        out.append(PaySummary(pay.stage, pay.task, pay.next_task, pay.threshold, paid, pay.rooms,
                              cell_scores(pay.reward)))
    return out


def _pay_json(run_dir: Path) -> dict[str, Any]:
    return {"stages": [{"stage": p.stage, "task": p.task, "next_task": p.next_task, "threshold": p.threshold,
                        "old_rooms_paid": None if math.isnan(p.old_rooms_paid) else p.old_rooms_paid,
                        "rooms": p.rooms, "reward_cells": _json_cells(p.reward_cells)}
                       for p in _pay_summaries(run_dir)]}


def _write_json(run_dir: Path, name: str, data: dict[str, Any]) -> None:
    atomic_write_text(run_dir / name, json.dumps(data, separators=(",", ":")) + "\n")


def _unit_name(cfg: Config) -> str:
    return f"{cfg.method.name}/seed{cfg.train.seed}"


def evaluate_unit(run_dir: str | Path) -> dict[str, float]:
    """Make every evaluation of the run's domain from its checkpoints and write each into its file.

    Returns:
        The CPU seconds of each evaluation made, by name.

    Raises:
        drago.training.rundir.RunDirError: no run directory or no finished task.
        drago.training.checkpoint.CheckpointError: a corrupt checkpoint.
    """
    from drago.eval.components import (COMPONENTS_FILE, SWAP_FILE, components_of_run, write_components_csv,
                                       write_swap_csv)
    from drago.eval.costs import COSTS_FILE, costs_of_run, write_costs_csv
    from drago.eval.heldout import RETENTION_FILE, retention_matrix, write_retention_csv
    from drago.eval.zero_shot import ZERO_SHOT_FILE, write_zero_shot_csv, zero_shot_matrix

    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir)
    seconds, zero_shot = {}, []
    for name in unit_evaluations(cfg):
        started = time.process_time()
        if name == "coverage":
            rows = [dict(r, run=_unit_name(cfg)) for r in coverage_of_run(run_dir)]
            write_coverage_csv(rows, run_dir / COVERAGE_FILE)
        elif name == "zero_shot":
            zero_shot = [dict(r, run=_unit_name(cfg)) for r in zero_shot_matrix(run_dir)]
            write_zero_shot_csv(zero_shot, run_dir / ZERO_SHOT_FILE)
        elif name == "cells":
            _write_json(run_dir, CELLS_FILE, _cells(run_dir))
        elif name == "reviewer_pay":
            _write_json(run_dir, REVIEWER_PAY_FILE, _pay_json(run_dir))
        elif name == "components":
            own = [r for r in zero_shot if task_room(r["task"]) is not None]
            rows, swaps = components_of_run(run_dir, own)
            write_components_csv(rows, run_dir / COMPONENTS_FILE)
            write_swap_csv(swaps, run_dir / SWAP_FILE)
        elif name == "costs":
            write_costs_csv(costs_of_run(run_dir), run_dir / COSTS_FILE)
        elif name == "retention":
            rows = [dict(r, run=_unit_name(cfg)) for r in retention_matrix(run_dir, record_missing=True)]
            write_retention_csv(rows, run_dir / RETENTION_FILE)
        seconds[name] = round(time.process_time() - started, 2)
    return seconds


def _transfer_configs(run_dir: Path) -> dict[str, Config]:
    return {config.parent.name: read_run_config(config.parent)
            for config in sorted((run_dir / TRANSFER_FOLDER).glob(f"*/{CONFIG_FILE}"))}


def record_unit(run_dir: str | Path, out: str | Path, evaluate: bool = True) -> dict[str, Any]:
    """A finished unit as a record: its evaluations (made now, unless ``evaluate`` is False), its protocol
    from what actually ran (the run's and its transfers' configs), written atomically to ``out``.

    Raises:
        RecordError: not a complete run, or a transfer case that has not finished.
    """
    from drago.training.rundir import is_complete

    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir)
    if not is_complete(run_dir):
        raise RecordError(f"{run_dir} has not finished every task; finish it (drago resume {run_dir}) first")
    transfers = _transfer_configs(run_dir)
    unfinished = [name for name in transfers if not is_complete(run_dir / TRANSFER_FOLDER / name)]
    if unfinished:
        raise RecordError(f"{run_dir}: the transfer case(s) {', '.join(unfinished)} have not finished; "
                          f"finish them first (drago resume {run_dir / TRANSFER_FOLDER / unfinished[0]})")
    seconds = evaluate_unit(run_dir) if evaluate else {}
    record = export_record(run_dir, unit_protocol(cfg, transfers), cfg)
    record["evaluation_cpu_s"] = seconds
    write_record(record, out)
    return record


def unit_cpu_seconds(record: Mapping[str, Any]) -> float:
    """The CPU seconds a recorded unit took: its run's tasks, its transfers and its evaluations."""
    total = sum(float(v) for v in (record.get("evaluation_cpu_s") or {}).values())
    for relative, text in record["files"].items():
        if relative == SUMMARY_FILE or (relative.startswith(f"{TRANSFER_FOLDER}/") and
                                        relative.count("/") == 2 and relative.endswith(f"/{SUMMARY_FILE}")):
            try:
                summary = json.loads(text)
            except json.JSONDecodeError:
                continue
            total += sum(float(t.get("cpu_time_s", 0.0)) for t in summary.get("tasks", []))
    return total


# ---- reading the evaluations back ------------------------------------------------------------------
def _read_json(run_dir: Path, name: str) -> dict[str, Any] | None:
    try:
        data = json.loads((Path(run_dir) / name).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return data if isinstance(data, dict) else None


def read_cells(run_dir: str | Path) -> list[tuple[RunCheckpoint, np.ndarray]] | None:
    """A record view's heatmap cells per stage (as :func:`~drago.report.heatmap.run_cell_scores` gives them
    from checkpoints), or None when the run has its checkpoints or no such file."""
    if not is_record_view(run_dir):
        return None
    data = _read_json(Path(run_dir), CELLS_FILE) or {"stages": []}
    return [(RunCheckpoint(int(s["stage"]), str(s["task"]), Path(run_dir) / "checkpoints" / "recorded"),
             _array_cells(s["cells"])) for s in data.get("stages", [])]


def read_reviewer_pay(run_dir: str | Path) -> list[PaySummary]:
    """What the reviewer was paid: from a record view's file, else computed from the checkpoints."""
    run_dir = Path(run_dir)
    if not is_record_view(run_dir):
        return _pay_summaries(run_dir)
    data = _read_json(run_dir, REVIEWER_PAY_FILE) or {"stages": []}
    return [PaySummary(int(s["stage"]), str(s["task"]), str(s["next_task"]), float(s["threshold"]),
                       math.nan if s.get("old_rooms_paid") is None else float(s["old_rooms_paid"]),
                       {k: dict(v) for k, v in s["rooms"].items()}, _array_cells(s["reward_cells"]))
            for s in data.get("stages", [])]

