"""The report's zero-shot section (grid runs): each stage's world model planned with the true reward.

The rows come from a run's ``zero_shot.csv`` (``drago eval zero-shot``) when it matches the run's checkpoints
and the evaluation's defaults, else they are computed here (about 3 s per run) and nothing is written into
the run. See docs: Evaluation, zero-shot planning.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from drago.envs import exact_world
from drago.eval.zero_shot import (
    DEFAULT_EPISODES,
    DEFAULT_EPSILON,
    DEFAULT_HORIZON,
    GRID_TASKS_TRAINING,
    ZERO_SHOT_FILE,
    ZeroShotError,
    default_tasks,
    is_paper_case,
    run_checkpoints,
    zero_shot_matrix,
)
from drago.report.content import Findings, Table
from drago.report.runs import ReportedRun, as_number
from drago.report.tables import format_summary
from drago.training.records import is_record_view


def zero_shot_rows(run: ReportedRun, findings: Findings) -> list[dict[str, Any]]:
    """The run's zero-shot rows at the evaluation's defaults (every task at its own reward reading)."""
    if exact_world(run.cfg.env.domain) is None:
        return []
    file = run.path / ZERO_SHOT_FILE
    if is_record_view(run.path):
        stages = {int(task["index"]) + 1 for task in (run.summary or {}).get("tasks", [])}
        rows = _own_rows(file)
        if rows is None:
            findings.missing.append(f"{run.shown}: its record has no readable {ZERO_SHOT_FILE}, so no zero-shot "
                                    "returns")
            return []
        return [r for r in rows if r["stage"] in stages and r["task"] in default_tasks(run.cfg.env.tasks)]
    try:
        _, checkpoints = run_checkpoints(run.path)
    except ZeroShotError:
        return []  # no finished stage: reported with the incomplete runs
    wanted = {(c.stage, task) for c in checkpoints for task in default_tasks(run.cfg.env.tasks)}
    why = "it has no zero_shot.csv"
    if file.is_file():
        own = _own_rows(file)
        if own is None:
            why = "its zero_shot.csv is unreadable"
        elif ({(r["stage"], r["task"]) for r in own} >= wanted
              and file.stat().st_mtime >= max(c.path.stat().st_mtime for c in checkpoints)
              and all((r["episodes"], r["horizon"], r["epsilon"]) == (DEFAULT_EPISODES, DEFAULT_HORIZON,
                                                                     DEFAULT_EPSILON) for r in own)):
            return [r for r in own if (r["stage"], r["task"]) in wanted]
        else:
            why = ("its zero_shot.csv is older than its checkpoints or was made with other tasks, episodes, horizon "
                   "or epsilon")
    findings.notes.append(f"{run.shown}: zero-shot returns computed from the checkpoints ({why}); nothing was "
                          "written")
    return zero_shot_matrix(run.path)


def _own_rows(file: Path) -> list[dict[str, Any]] | None:
    """A zero_shot.csv's rows at each task's own reward (training rooms dense, transfers sparse), numbers as
    numbers; None if it is missing or unreadable."""
    try:
        with file.open(newline="") as handle:
            # A file from before epsilon existed was made deterministically: its rows do not match.
            rows = [dict(r, stage=int(r["stage"]), fraction=as_number(r["fraction"]), episodes=int(r["episodes"]),
                         horizon=int(r["horizon"]), epsilon=as_number(r.get("epsilon")))
                    for r in csv.DictReader(handle)]
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, ValueError, TypeError):
        return None
    return [r for r in rows if r["reward"] == ("dense" if r["task"] in GRID_TASKS_TRAINING else "sparse")]


def zero_shot_table(groups: dict[str, list[ReportedRun]], rows: dict[Path, list[dict[str, Any]]]) -> Table | None:
    """Mean ± std [95% CI] over seeds of each (stage, task) cell's fraction of the DP optimum."""
    tasks = list(dict.fromkeys(r["task"] for run_rows in rows.values() for r in run_rows))
    if not tasks:
        return None
    out = []
    for label, runs in groups.items():
        cells = [{(r["stage"], r["task"]): (r["fraction"], is_paper_case(r)) for r in rows.get(run.path, [])}
                 for run in runs]
        cells = [c for c in cells if c]
        for stage in sorted({stage for c in cells for stage, _ in c}):
            reached = [c for c in cells if any(s == stage for s, _ in c)]
            after = next(run.planned[stage - 1] for run in runs if len(run.planned) >= stage)
            row = [label, f"{stage}: {after}", str(len(reached))]
            for task in tasks:
                values = [c[(stage, task)][0] for c in reached if (stage, task) in c]
                case = any(c[(stage, task)][1] for c in reached if (stage, task) in c)
                row.append((format_summary(values)[0] + (" *" if case else "")) if values else "–")
            out.append(tuple(row))
    return Table("zero-shot", "Zero-shot planning with the retained world model",
                 "The return of planning with the world model after each stage and the task's true reward, no "
                 "learned head and no learning, as a fraction of the task's DP optimum (training rooms dense, "
                 "transfer tasks sparse; an exhaustive lookahead to the end of the episode, with "
                 f"{DEFAULT_EPSILON:g} of the steps random so that one wrong transition on the route does not trap "
                 "the planner; with the true dynamics this reaches 0.93-0.97 of every task's optimum, 1 with no "
                 "random steps). * marks the paper's four transfer cases. Mean ± std [95% CI] over seeds.",
                 ("method", "after stage", "seeds", *tasks), out)


def zero_shot_matrix_of(run: ReportedRun, rows: list[dict[str, Any]]) -> list[list[float]]:
    """R[i][j] = zero-shot fraction on the run's task j after stage i + 1, over the stages the run finished
    (the rows of a run's training rooms, in the run's order)."""
    fraction = {(r["stage"], r["task"]): float(r["fraction"]) for r in rows}
    if not run.planned:
        return []
    stages = 0
    while all((stages + 1, task) in fraction for task in run.planned):
        stages += 1
    return [[fraction[(i + 1, task)] for task in run.planned] for i in range(stages)]
