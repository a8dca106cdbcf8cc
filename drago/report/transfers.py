"""The report's tables of transfer runs (paper §4.4): few-shot scores read two ways, the learners'
own returns, and the relearning matrix of training tasks."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from drago.report.content import Findings, Table
from drago.report.runs import EVAL_FILE, Case, ReportedRun, as_number, case_name
from drago.report.tables import format_summary, metrics_table
from drago.training.rundir import RunDirError, atomic_write_text, is_run_dir, read_run_config, read_summary
from drago.training.transfer import training_returns, transfer_summary

TRANSFERS_CSV = "transfers.csv"
TRANSFERS_MD = "transfers.md"
TRANSFER_COLUMNS = ("method", "seed", "task", "after", "complete", "few_shot_episodes", "optimal_return",
                    "return_equal_episodes", "fraction_equal_episodes", "return_equal_env_steps",
                    "fraction_equal_env_steps", "total_env_steps", "wall_time_s", "directory")

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


def transfer_block(run: ReportedRun) -> dict[str, Any] | None:
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
    shown = [f"{n:.{digits}f}" for n in (as_number(v) for v in values) if math.isfinite(n)]
    return ", ".join(dict.fromkeys(shown)) or "–"


def _by_case(tgroups: dict[str, list[ReportedRun]], cases: list[Case]) -> Iterator[tuple[Case, str, list[ReportedRun]]]:
    """(case, method label, that method's transfers of the case) for every pair that has any."""
    for case in cases:
        for label, runs in tgroups.items():
            mine = [run for run in runs if run.case == case]
            if mine:
                yield case, label, mine


def transfer_tables(tgroups: dict[str, list[ReportedRun]], cases: list[Case],
                     blocks: dict[Path, dict[str, Any] | None]) -> list[Table]:
    tables = []
    for which, key, title, caption in _FEW_SHOT:
        rows = []
        for case, label, mine in _by_case(tgroups, cases):
            points = [p for p in ((blocks[run.path] or {}).get("few_shot", {}).get(which) for run in mine) if p]
            fraction, _ = format_summary([as_number(p.get("fraction_of_optimal")) for p in points])
            returns, _ = format_summary([as_number(p.get("return")) for p in points])
            rows.append((case_name(case), label, str(len(points)), _distinct(p.get("episode") for p in points),
                         _distinct(p.get("total_env_steps") for p in points), fraction, returns,
                         _distinct(((blocks[run.path] or {}).get("optimal_return") for run in mine), 1)))
        tables.append(Table(key, title, caption, ("case", "method", "seeds", "learner episodes", "total env steps",
                                                  "fraction of optimum", "return", "optimum"), rows))
    return tables


def training_table(tgroups: dict[str, list[ReportedRun]], cases: list[Case]) -> Table:
    """The learners' own episode returns over the few-shot episodes (:func:`training_returns`)."""
    rows = []
    for case, label, mine in _by_case(tgroups, cases):
        done = [t for t in (training_returns(run.cfg, run.path) for run in mine) if t]
        mean_return, _ = format_summary([t["mean_return"] for t in done])
        positive, _ = format_summary([t["positive_episodes"] for t in done])
        rows.append((case_name(case), label, str(len(done)), _distinct(t["episodes"] for t in done),
                     mean_return, positive))
    return Table("transfer-training", "Transfer: the learner's return while it learns",
                 "The learner's own exploring episodes during the few-shot episodes (train.csv, not evaluations): "
                 "the mean return per episode, and how many episodes had a positive return. On a sparse-reward "
                 "grid task a positive return means the goal was reached, which the learner must see before its "
                 "planner can head there; an evaluation return of 0 with no such episode says the goal was never "
                 "found. Mean ± std [95% CI] over the seeds that have played every few-shot episode.",
                 ("case", "method", "seeds", "learner episodes", "mean episode return",
                  "episodes with a positive return"), rows)


def _source_run(transfer: ReportedRun) -> Path:
    """The run directory whose stage checkpoint a transfer started from (``RUN_DIR/checkpoints/*.pt``)."""
    return (transfer.path / str(transfer.cfg.transfer.checkpoint)).resolve().parent.parent


def _relearning_matrix(run: ReportedRun, relearned: dict[tuple[str, int], float],
                       findings: Findings) -> list[list[float]]:
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
        findings.missing.append(f"{run.shown}: its relearning matrix stops at T = {stages}; it lacks "
                                f"{', '.join(lacking[:4])}{' ...' if len(lacking) > 4 else ''} "
                                f"(`drago transfer {run.shown} --task TASK --after K`)")
    return [[relearned[(run.planned[j], i + 1)] for j in range(stages)] for i in range(stages)]


def relearning_metrics(groups: dict[str, list[ReportedRun]], transfers: list[ReportedRun],
                        blocks: dict[Path, dict[str, Any] | None], findings: Findings) -> list[Table]:
    """Continual-learning metrics of the return matrix: each training task relearned after each stage."""
    relearned: dict[Path, dict[tuple[str, int], float]] = {}
    for transfer in transfers:
        task, after = transfer.case
        point = (blocks[transfer.path] or {}).get("few_shot", {}).get("equal_episodes")
        if not point:
            continue  # not reached yet; test tasks never match a training task in _relearning_matrix
        fraction = as_number(point.get("fraction_of_optimal"))
        relearned.setdefault(_source_run(transfer), {})[(task, after)] = (
            fraction if math.isfinite(fraction) else as_number(point.get("return")))
    matrices = {run.path: _relearning_matrix(run, relearned.get(run.path.resolve(), {}), findings)
                for runs in groups.values() for run in runs}
    if not any(matrices.values()):
        return []
    return [metrics_table(groups, matrices, "relearning-metrics", "Continual-learning metrics (from relearning)",
                           "the few-shot score (fraction of the DP optimum on the grid, raw return on DeepMind "
                           "Control) of relearning training task j with fresh heads (`drago transfer RUN --task "
                           "TASK_j --after i+1`) from the world model saved")]


def transfer_gaps(groups: dict[str, list[ReportedRun]], tgroups: dict[str, list[ReportedRun]], cases: list[Case],
                   blocks: dict[Path, dict[str, Any] | None], findings: Findings) -> None:
    """Unfinished transfers, scores not reached, cases some method or seed lacks, uneven few-shot episodes."""
    for label, runs in tgroups.items():
        for run in runs:
            where = f"{run.shown} ({label}, seed {run.seed}, {case_name(run.case)})"
            block = blocks[run.path]
            if block is None:
                findings.missing.append(f"{where}: no few-shot scores (unreadable {EVAL_FILE})")
                continue
            parts = []
            if not run.complete:
                done = max((int(e) for e in (as_number(r.get("episode")) for r in run.eval_rows) if math.isfinite(e)),
                           default=0)
                parts.append(f"unfinished, {done} of {block.get('episodes_planned')} learner episodes evaluated")
            absent = [what.replace("_", " ") for what in ("equal_episodes", "equal_env_steps")
                      if not block["few_shot"].get(what)]
            if absent:
                parts.append(f"no few-shot score at {' or '.join(absent)} yet")
            if parts:
                findings.missing.append(f"{where}: {'; '.join(parts)}")
    domains = {run.case: run.cfg.env.domain for runs in tgroups.values() for run in runs}

    def applies(run: ReportedRun, case: Case) -> bool:  # a sequence run that could have this transfer
        return run.cfg.env.domain == domains[case] and case[1] <= len(run.planned)

    for label in dict.fromkeys([*groups, *tgroups]):
        transfers, sequence = tgroups.get(label, []), groups.get(label, [])
        for case in cases:
            expected = {run.seed for run in transfers} | {run.seed for run in sequence if applies(run, case)}
            have = sorted(run.seed for run in transfers if run.case == case)
            lacking = sorted(expected - set(have))
            if lacking:
                findings.missing.append(f"{label}: no transfer {case_name(case)} for seed(s) "
                                        f"{', '.join(map(str, lacking))}")
            repeated = sorted({s for s in have if have.count(s) > 1})
            if repeated:
                findings.missing.append(f"{label}: seed(s) {', '.join(map(str, repeated))} of transfer "
                                        f"{case_name(case)} appear in more than one run, so those runs are not "
                                        f"independent samples")
    for case in cases:
        episodes = {label: _distinct((blocks[run.path] or {}).get("few_shot_episodes") for run in runs
                                     if run.case == case) for label, runs in tgroups.items()}
        episodes = {label: e for label, e in episodes.items() if e != "–"}
        if len(set(episodes.values())) > 1 or any("," in e for e in episodes.values()):
            findings.missing.append(f"{case_name(case)}: few-shot scores read after different numbers of learner "
                                    f"episodes ({'; '.join(f'{k}: {v}' for k, v in episodes.items())}), so they "
                                    f"do not compare")


# ---- the study's transfer tables: one row per case and seed, and the same statistic as the report ----
def transfer_rows(transfer_dirs: Iterable[Path], names: Mapping[Path, str] | None = None) -> list[dict[str, Any]]:
    """One row per transfer directory that has a summary: its few-shot scores, read both ways (paper §4.4).
    ``names`` says how to name a directory in the rows (a record view's, by its record); default its path."""
    rows = []
    for directory in transfer_dirs:
        if not is_run_dir(directory):
            continue
        try:
            cfg = read_run_config(directory)
            summary = read_summary(directory)
        except RunDirError:
            continue
        block = (summary or {}).get("transfer")
        if not isinstance(block, dict):
            continue
        few = block.get("few_shot") or {}
        at_episodes, at_steps = few.get("equal_episodes") or {}, few.get("equal_env_steps") or {}
        rows.append({"method": cfg.method.name, "seed": cfg.train.seed, "task": block.get("task"),
                     "after": block.get("after"), "complete": summary.get("complete") is True,
                     "few_shot_episodes": block.get("few_shot_episodes"),
                     "optimal_return": block.get("optimal_return"),
                     "return_equal_episodes": at_episodes.get("return"),
                     "fraction_equal_episodes": at_episodes.get("fraction_of_optimal"),
                     "return_equal_env_steps": at_steps.get("return"),
                     "fraction_equal_env_steps": at_steps.get("fraction_of_optimal"),
                     "total_env_steps": block.get("total_env_steps"), "wall_time_s": block.get("wall_time_s"),
                     "directory": (names or {}).get(directory, str(directory))})
    return rows


def write_transfer_tables(transfer_dirs: Iterable[Path], out_dir: Path,
                          names: Mapping[Path, str] | None = None) -> list[Path]:
    """``transfers.csv`` (one row per case and seed) and ``transfers.md`` (mean ± std [95% CI] over seeds,
    the report's statistic) for the transfer directories that have a summary; nothing if none has.
    ``names``: as in :func:`transfer_rows`."""
    rows = transfer_rows(transfer_dirs, names)
    if not rows:
        return []
    handle = io.StringIO(newline="")
    writer = csv.DictWriter(handle, fieldnames=TRANSFER_COLUMNS)
    writer.writeheader()
    writer.writerows({k: ("" if v is None else v) for k, v in row.items()} for row in rows)
    csv_path = atomic_write_text(Path(out_dir) / TRANSFERS_CSV, handle.getvalue())
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cases = list(dict.fromkeys((r["task"], r["after"]) for r in rows))
    optimum = {(r["task"], r["after"]): r["optimal_return"] for r in rows}
    lines = ["# Transfers: few-shot return", "",
             "Evaluation return on each test task learned from the world model saved after stage K (paper §4.4): "
             "mean ± std [95% bootstrap CI of the mean] over seeds, as in the report; a single seed shows its value "
             "alone. Rows of unfinished cases are left out until they reach the score. Per-seed values and "
             f"fractions of the DP optimum are in `{TRANSFERS_CSV}`; each case's curves in its `eval.csv`."]
    for key, title in (("return_equal_episodes", "after the same number of learner episodes (the paper's reading)"),
                       ("return_equal_env_steps", "at the same total env steps (a reviewer's steps counted)")):
        lines += ["", f"## {title.capitalize()}", "",
                  "| case | optimum | " + " | ".join(methods) + " |",
                  "|---|---|" + "---|" * len(methods)]
        for task, after in cases:
            cells = []
            for method in methods:
                values = [r[key] for r in rows if r["method"] == method and (r["task"], r["after"]) == (task, after)
                          and r[key] is not None]
                text, n = format_summary(values)
                cells.append(f"{text} ({n})" if n else text)
            best = optimum[(task, after)]
            shown = "" if best is None else f"{best:.1f}"
            lines.append(f"| {task} after {after} | {shown} | " + " | ".join(cells) + " |")
    md_path = atomic_write_text(Path(out_dir) / TRANSFERS_MD, "\n".join(lines) + "\n")
    return [csv_path, md_path]
