"""The report's tables of continual runs: returns, forward transfer, coverage, retention and their metrics."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from drago.envs import exact_world
from drago.eval.coverage import (
    ALL,
    COVERAGE_FILE,
    ROOM_GROUPS,
    CoverageError,
    coverage_of_run,
    run_checkpoints,
    task_room,
)
from drago.eval.metrics import continual_metrics, cw_forward_transfer
from drago.eval.stats import summarize
from drago.report.content import Findings, Table
from drago.report.runs import EVAL_FILE, ReportedRun, as_number, quantity_of
from drago.training.records import is_record_view
from drago.training.rundir import SUMMARY_FILE

DIGITS = 2
COVERAGE_COLUMNS = (*ROOM_GROUPS, ALL)


def format_summary(values: Sequence[float]) -> tuple[str, int]:
    summary = summarize(values)
    return summary.format(DIGITS), summary.n


def _wall_time(seconds: Any) -> str:
    s = as_number(seconds)
    if not math.isfinite(s):
        return "–"
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def runs_table(groups: dict[str, list[ReportedRun]]) -> Table:
    rows = []
    for label, runs in groups.items():
        for run in runs:
            wall = (run.summary or {}).get("wall_time_s")
            tasks = run.finished.values()
            learner = sum(int(t.get("learner_steps", t.get("steps", 0))) for t in tasks) * run.cfg.env.action_repeat
            total = sum(int(t.get("env_steps", 0)) for t in tasks)
            cpu = sum(float(t.get("cpu_time_s", 0.0)) for t in tasks)
            rows.append((label, str(run.seed), run.cfg.preset, "yes" if run.complete else "no",
                         f"{len(run.finished)}/{len(run.planned)}", f"{learner:,}", f"{total:,}", _wall_time(wall),
                         _wall_time(cpu) if cpu else "–", run.shown))
    return Table("runs", "Runs", "One row per run directory, summed over its finished tasks: the learner's env "
                 "steps, all env steps (the learner's and, for DRAGO, its reviewer's), wall time, and CPU time "
                 "(all threads; unlike wall time, it does not depend on what else the machine was doing).",
                 ("method", "seed", "preset", "complete", "tasks done", "learner env steps", "env steps",
                  "wall time", "CPU time", "run directory"), rows)


def returns_table(groups: dict[str, list[ReportedRun]], tasks: list[str]) -> Table:
    rows = []
    for label, runs in groups.items():
        for task in tasks:
            entries = [run.finished[task] for run in runs if task in run.finished]
            if not entries:
                continue
            fraction, _ = format_summary([as_number(e.get("fraction_of_optimal")) for e in entries])
            returns, _ = format_summary([as_number(e.get("final_eval_return")) for e in entries])
            optima = [o for o in (as_number(e.get("optimal_return")) for e in entries) if math.isfinite(o)]
            rows.append((label, task, str(len(entries)), fraction, returns, f"{optima[0]:.1f}" if optima else "–"))
    return Table("returns", "Final return per task",
                 "Evaluation return at the end of each task, and as a fraction of the DP-optimal return of "
                 "that task where one is known (the grid; not DeepMind Control): mean ± sample std [95% "
                 "bootstrap CI of the mean] over seeds; a single seed shows its value alone. Seeds counts only "
                 "runs that finished the task.",
                 ("method", "task", "seeds", "fraction of optimum", "return", "DP optimum"), rows)


def _task_curve(run: ReportedRun, task: str) -> tuple[dict[int, float], float]:
    """A finished task's evaluation curve (task env step -> value) and the best value its scale allows:
    1 for the fraction of the DP optimum (grid), the most a DeepMind Control episode can earn for raw
    return (reward at most 1 per control step)."""
    if task not in run.finished:
        return {}, math.nan
    rows = [r for r in run.eval_rows if r["task"] == task]
    key, _ = quantity_of(rows)
    ceiling = 1.0 if key == "fraction_of_optimal" else float(run.cfg.env.episode_length * run.cfg.env.action_repeat)
    curve = {int(as_number(r["env_step"])): as_number(r[key]) for r in rows}
    return {x: y for x, y in curve.items() if math.isfinite(y)}, ceiling


def forward_transfer_table(groups: dict[str, list[ReportedRun]], tasks: list[str], findings: Findings) -> list[Table]:
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
                    findings.notes.append(f"{run.shown}: no forward transfer on {task} ({err})")
            if transfer:
                per_run.append(transfer)
        if per_run:
            means = [sum(t.values()) / len(t) for t in per_run]
            cells = [format_summary([t[task] for t in per_run if task in t])[0]
                     if any(task in t for t in per_run) else "–" for task in tasks]
            rows.append((label, str(len(per_run)), format_summary(means)[0], *cells))
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


def coverage_rows(run: ReportedRun, findings: Findings) -> list[dict[str, Any]]:
    """The run's coverage rows: its coverage.csv when it matches its checkpoints, else computed."""
    if exact_world(run.cfg.env.domain) is None:
        return []  # its retention matrix comes from held-out sets instead
    if is_record_view(run.path):
        rows = _read_coverage(run.path / COVERAGE_FILE)
        if rows is None:
            findings.missing.append(f"{run.shown}: its record has no readable {COVERAGE_FILE}, so no coverage")
        return rows or []
    try:
        _, checkpoints = run_checkpoints(run.path)
    except CoverageError:
        return []  # no finished task: reported with the incomplete runs
    stages = {c.stage for c in checkpoints}
    file = run.path / COVERAGE_FILE
    if file.is_file():
        rows = _read_coverage(file)
        if rows is None:
            why = "its coverage.csv is unreadable"
        elif {r["stage"] for r in rows} == stages and file.stat().st_mtime >= max(c.path.stat().st_mtime
                                                                                  for c in checkpoints):
            return rows
        else:
            why = "its coverage.csv is older than or does not match its checkpoints"
    else:
        why = "it has no coverage.csv"
    findings.notes.append(f"{run.shown}: coverage computed from the checkpoints ({why}); nothing was written")
    return coverage_of_run(run.path)


def _read_coverage(file: Path) -> list[dict[str, Any]] | None:
    """A coverage.csv's rows with numbers as numbers, or None if it is unreadable."""
    try:
        with file.open(newline="") as handle:
            return [dict(r, stage=int(r["stage"]), accuracy=as_number(r["accuracy"]), score=as_number(r["score"]))
                    for r in csv.DictReader(handle)]
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, ValueError, TypeError):
        return None


def _accuracy(rows: list[dict[str, Any]]) -> dict[tuple[int, str], float]:
    return {(int(r["stage"]), r["room"]): float(r["accuracy"]) for r in rows}


def coverage_table(groups: dict[str, list[ReportedRun]], coverage: dict[Path, list[dict[str, Any]]]) -> Table:
    rows = []
    for label, runs in groups.items():
        by_run = [(_accuracy(coverage[run.path]), run) for run in runs if coverage.get(run.path)]
        stages = sorted({stage for acc, _ in by_run for stage, _ in acc})
        for stage in stages:
            reached = [(acc, run) for acc, run in by_run if (stage, ALL) in acc]
            task = reached[0][1].planned[stage - 1]
            cells = [format_summary([acc[(stage, room)] for acc, _ in reached])[0] for room in COVERAGE_COLUMNS]
            rows.append((label, f"{stage}: {task}", str(len(reached)), *cells))
    return Table("coverage", "World-model coverage",
                 "Exact-match accuracy of the world model after each stage: the share of the grid's "
                 "transitions (cell × heading × action) in each room whose predicted next state decodes "
                 "to the true one; 'all' includes the five centre openings. Mean ± std [95% CI] over seeds.",
                 ("method", "after stage", "seeds", *COVERAGE_COLUMNS), rows)


def coverage_matrix(run: ReportedRun, rows: list[dict[str, Any]], findings: Findings) -> list[list[float]]:
    """R[i][j] = coverage accuracy in the room of task j after stage i + 1, over the stages the run finished."""
    acc = _accuracy(rows)
    if not acc:
        return []
    rooms = [task_room(task) for task in run.planned]
    if None in rooms:
        findings.missing.append(f"{run.shown}: continual metrics need one room per task; "
                                f"{', '.join(t for t, r in zip(run.planned, rooms) if r is None)} has none")
        return []
    stages = 0
    while (stages + 1, ALL) in acc:
        stages += 1
    if stages == 0:
        findings.missing.append(f"{run.shown}: no world model after task 1, so no continual metrics")
    return [[acc[(i + 1, room)] for room in rooms] for i in range(stages)]


def retention_score_matrix(rows: list[dict[str, Any]]) -> list[list[float]]:
    """R[i][j] = held-out prediction score of task j's set after stage i + 1, over the largest T for which
    every stage i < T has a score on every set j < T (a missing set shortens T)."""
    score = {(int(r["stage"]), int(r["task_stage"])): float(r["score"]) for r in rows}
    stages = 0
    while all((i, j) in score for i in range(1, stages + 2) for j in range(1, stages + 2)):
        stages += 1
    return [[score[(i + 1, j + 1)] for j in range(stages)] for i in range(stages)]


def metrics_table(groups: dict[str, list[ReportedRun]], matrices: dict[Path, list[list[float]]], table_id: str,
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
            cells = [format_summary([m[key] for m in metrics])[0] for key in ("acc", "bwt", "forgetting")]
            rows.append((label, str(stages), str(len(metrics)), *cells))
    return Table(table_id, title,
                 f"R[i, j] = {what} after stage i, over the T stages a run finished. ACC (GEM) = mean over j of "
                 "R[T-1, j], equal to Continual World's average performance; BWT (GEM) = mean over j < T-1 of "
                 "R[T-1, j] − R[j, j], negative when the model forgets; forgetting (Continual World) = −BWT. "
                 "Runs are grouped by T, since values over different T do not compare; with T = 1 there is "
                 "nothing to forget (–).",
                 ("method", "stages T", "seeds", "ACC", "BWT", "forgetting"), rows)


def retention_rows(run: ReportedRun, findings: Findings) -> list[dict[str, Any]]:
    """A DeepMind Control run's retention rows from its held-out sets on disk (none is recorded here)."""
    from drago.eval.heldout import HeldoutError, heldout_checkpoints, heldout_path, retention_matrix

    if exact_world(run.cfg.env.domain) is not None:
        return []
    if is_record_view(run.path):
        return _read_retention(run, findings)
    try:
        _, checkpoints = heldout_checkpoints(run.path)
    except HeldoutError:
        return []  # no finished task: reported with the incomplete runs
    missing = [c.task for c in checkpoints if not heldout_path(run.path, c.stage, c.task).is_file()]
    if missing:
        why = ("it was trained with train.heldout_episodes=0" if run.cfg.train.heldout_episodes == 0
               else f"`drago eval heldout {run.shown}` records them from the checkpoints")
        findings.missing.append(f"{run.shown}: no held-out set for {', '.join(missing)}, so the retention matrix "
                                f"lacks {'that column' if len(missing) == 1 else 'those columns'} ({why})")
    return retention_matrix(run.path) if len(missing) < len(checkpoints) else []


def _read_retention(run: ReportedRun, findings: Findings) -> list[dict[str, Any]]:
    from drago.eval.heldout import RETENTION_FILE

    try:
        with (run.path / RETENTION_FILE).open(newline="") as handle:
            return [dict(r, seed=int(r["seed"]), stage=int(r["stage"]), task_stage=int(r["task_stage"]),
                         error=as_number(r["error"]), score=as_number(r["score"]), n=int(r["n"]))
                    for r in csv.DictReader(handle)]
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, ValueError, TypeError):
        findings.missing.append(f"{run.shown}: its record has no readable {RETENTION_FILE}, so no retention matrix")
        return []


def retention_tables(groups: dict[str, list[ReportedRun]], rows: dict[Path, list[dict[str, Any]]]) -> list[Table]:
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
            scores = (format_summary([v[0] for v in vs])[0] for vs in values)
            score_rows.append((label, stage, str(len(seeds[key])), *scores))
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


def find_gaps(groups: dict[str, list[ReportedRun]], tasks: list[str], findings: Findings) -> None:
    """Incomplete runs, missing checkpoints and files, uneven seeds and unreached tasks."""
    for runs in groups.values():
        for run in runs:
            where = f"{run.shown} ({run.label}, seed {run.seed})"
            if run.summary is None:
                findings.missing.append(f"{where}: no {SUMMARY_FILE}, no task finished yet")
            elif not run.complete:
                left = [t for t in run.planned if t not in run.finished]
                findings.missing.append(f"{where}: incomplete, {len(run.finished)} of {len(run.planned)} tasks "
                                        f"finished; not reached: {', '.join(left)}")
            for name, entry in run.finished.items():
                checkpoint = entry.get("checkpoint")
                if checkpoint and not is_record_view(run.path) and not (run.path / checkpoint).is_file():
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
