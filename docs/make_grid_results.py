"""Regenerate the grid study's section of the results page from the committed records.

    .venv/bin/python docs/make_grid_results.py [--records results/grid] [--reviewer-records results/grid-reviewer]
        [--reviewer-2x-records results/grid-reviewer-2x] [--dense-records results/grid-dense] [--preset minigrid-cpu]

Reads every record of the main study (``drago study --records results/grid``) and of its side studies where
they have records (does the reviewer regain anything: ``drago-no-rehearsal`` paid against a lowered θ, and the
same beside ``continual`` at twice the task budget; transfer that can learn: the transfer cases with dense
reward), writes the per-unit numbers the section shows into ``docs/data/grid_*records_*.csv``, builds the
reports of the records into ``docs/grid-report/``, ``docs/grid-reviewer-2x-report/`` and
``docs/grid-dense-report/`` (report.md and its figures), and rewrites the part of ``docs/results.md`` between
the markers ``<!-- grid-records:start -->`` and ``<!-- grid-records:end -->``: what is recorded and what is
left, and the paper's claims, each with its verdict from the records with 95% CIs, or the seeds it still waits
for. Nothing else is read: no run directories, no checkpoints. The same records give the same files.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from drago.eval.stats import summarize
from drago.study.plan import DEFAULT_METHODS, DEFAULT_SEEDS
from drago.training.records import find_records, read_record

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
_docs = DOCS  # where the files are written: the docs folder, or --docs (a copy, for tests)
START, END = "<!-- grid-records:start -->", "<!-- grid-records:end -->"
ROOMS = ("room1", "room2", "room3", "room4")
LEARNED = 0.80  # a room counts as learned at this fraction of its DP optimum at its task's end (issue's bar)
# A task's final evaluation is a small sample of episodes; its last training episodes say whether the learner had
# settled: the share of them that reached half the optimum (a dense return that low means the goal came late or
# never).
LATE_EPISODES = 20


def _late_success(train_rows: list[dict[str, str]], optimum: dict[str, float]) -> dict[str, float]:
    """Per task, the share of its last ``LATE_EPISODES`` learner training episodes at ≥ half its DP optimum."""
    returns = defaultdict(list)
    for r in train_rows:
        returns[r["task"]].append(float(r["episode_reward"]))
    return {task: float(np.mean([v >= 0.5 * optimum[task] for v in values[-LATE_EPISODES:]]))
            for task, values in returns.items() if optimum.get(task)}


def _csv(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def _fmt(values: list[float]) -> str:
    if not values:
        return "–"
    return summarize(values).format(2) if len(values) > 1 else f"{values[0]:.2f} (1 seed)"


def _ci(values: list[float]) -> tuple[float, float]:
    s = summarize(values)
    return s.ci_low, s.ci_high


def load(folder: Path, preset: str = "minigrid-cpu") -> list[dict]:
    units = []
    for path in find_records(folder):
        record = read_record(path)
        if record["unit"]["preset"] != preset:
            print(f"left out {path}: preset {record['unit']['preset']}, not the grid study's {preset}")
            continue
        files = record["files"]
        summary = json.loads(files["summary.json"])
        coverage = _csv(files.get("coverage.csv", ""))
        zero = _csv(files.get("zero_shot.csv", ""))
        transfers = {}  # case -> reading -> fraction of the test task's optimum
        transfer_episodes = 0  # the learner episodes of the longest transfer case
        for name, text in files.items():
            if name.startswith("transfer/") and name.endswith("/summary.json") and name.count("/") == 2:
                case = name.split("/")[1]
                block = json.loads(text).get("transfer") or {}
                few_shot = block.get("few_shot") or {}
                transfer_episodes = max(transfer_episodes, int((block.get("final") or {}).get("episode") or 0))
                curve = [(int(r["episode"]), float(r["fraction_of_optimal"]))
                         for r in _csv(files.get(f"transfer/{case}/eval.csv", ""))
                         if r.get("fraction_of_optimal") not in (None, "")]
                transfers[case] = {"reward": block.get("reward"),
                                   **{reading: (few_shot.get(reading) or {}).get("fraction_of_optimal")
                                      for reading in TRANSFER_READINGS[:2]},
                                   **curve_readings(curve)}
        components = defaultdict(dict)  # (stage, task) -> component -> value
        stage_tasks = {}  # stage -> the task trained in it
        for r in _csv(files.get("components.csv", "")):
            stage_tasks[int(r["stage"])] = r["stage_task"]
            if r.get("value") not in (None, "", "nan"):
                components[(int(r["stage"]), r["task"])][r["component"]] = float(r["value"])
        swap = {}
        for r in _csv(files.get("swap.csv", "")):
            optimum = float(r["optimum"])
            swap[(int(r["stage"]), r["task"])] = {column: float(r[column]) / optimum
                                                 for column in SWAP_READINGS if r.get(column) not in (None, "")}
        costs = _csv(files.get("costs.csv", ""))
        optimum = {t["name"]: t.get("optimal_return") for t in summary["tasks"]}
        settings = record["protocol"]["run"]
        units.append({"path": path,
                      "env_steps": (sum(int(r["learner_env_steps"]) for r in costs),
                                    sum(int(r["reviewer_env_steps"]) for r in costs)) if costs else None,
                      "method": record["unit"]["method"], "seed": record["unit"]["seed"],
                      "digest": record["protocol"]["digest"], "provenance": record["provenance"],
                      "threshold_offset": float(settings.get("method.reviewer.threshold_offset") or 0.0),
                      "steps_per_task": settings.get("train.steps_per_task"),
                      "final": {t["name"]: t["fraction_of_optimal"] for t in summary["tasks"]},
                      "late_success": _late_success(_csv(files.get("train.csv", "")), optimum),
                      "cpu_h": sum(float(t.get("cpu_time_s") or 0) for t in summary["tasks"]) / 3600,
                      "coverage": {(int(r["stage"]), r["room"]): float(r["accuracy"]) for r in coverage},
                      "zero_shot": {(int(r["stage"]), r["task"]): float(r["fraction"]) for r in zero
                                    if r.get("fraction") not in (None, "")},
                      "transfers": transfers, "transfer_episodes": transfer_episodes,
                      "components": dict(components), "swap": swap,
                      "stage_tasks": stage_tasks,
                      "evaluations": record["protocol"].get("evaluations", [])})
    return units


#: A transfer case's readings: the few-shot score at equal learner episodes and at equal env steps (the study's
#: few-shot episodes), the mean over its learning curve and the curve's end; each a fraction of the test task's
#: optimum.
TRANSFER_READINGS = ("equal_episodes", "equal_env_steps", "curve_mean", "curve_end")


def curve_readings(curve: list[tuple[int, float]]) -> dict[str, float | None]:
    """A transfer's learning curve, its evaluations in order as (learner episodes, fraction of the optimum), read
    three ways: its mean, how fast it learned rather than where it stood at one episode; its end, the mean of its
    last tenth of evaluations (at least one), where it got to; and the learner episodes it took to first evaluate
    at half the optimum (None if it never did). A transfer on the grid either finds its goal and climbs to the
    optimum or never finds it, and the mean alone cannot tell a late climb from a half-way plateau."""
    if not curve:
        return {"curve_mean": None, "curve_end": None, "episodes_to_half": None}
    fractions = [fraction for _, fraction in curve]
    return {"curve_mean": float(np.mean(fractions)),
            "curve_end": float(np.mean(fractions[-max(1, len(fractions) // 10):])),
            "episodes_to_half": next((episode for episode, fraction in curve if fraction >= 0.5), None)}


#: The grid's test tasks (the transfer cases' tasks) the zero-shot claim averages over.
TEST_TASKS = ("room1to2", "room1to3", "room3to4")
#: The screenshot of the records' report, drawn in a fresh clone (docs/make_report_screenshots.py).
SCREENSHOT = "report-records-top.png"
#: The swap test's returns (swap.csv), read as fractions of each task's DP optimum.
SWAP_READINGS = ("saved", "moved", "refit", "true_reward")
#: The rows of the "which part forgot" table: (source, key, what the row says).
FORGOT_ROWS = (
    ("components", "dynamics_1step", "dynamics, 1 step (share exact)"),
    ("components", "dynamics_hstep", "dynamics, H steps (share exact)"),
    ("components", "reward_error", "reward head error (MAE)"),
    ("components", "value_order", "value order (rank corr. with Q*)"),
    ("components", "policy_agreement", "policy = optimal action (share)"),
    ("swap", "saved", "return: model and heads saved after the task (a)"),
    ("swap", "moved", "return: last model under the saved heads (b)"),
    ("swap", "refit", "return: last model, heads refit (c)"),
    ("swap", "true_reward", "return: last model, true reward (d)"),
)
#: The dense transfers' methods, in the order the issue names them, and the readings their table shows.
DENSE_METHODS = ("drago", "continual", "replay", "scratch")
DENSE_READINGS = (("equal_episodes", "few-shot at equal learner episodes"),
                  ("equal_env_steps", "few-shot at equal env steps"),
                  ("curve_mean", "mean over the learning curve"),
                  ("curve_end", "end of the learning curve, its last tenth"))
#: The methods of the "which part forgot" table, in the order the issue names them first.
FORGOT_METHODS = ("drago", "continual", "ewc", "replay", "drago-no-rehearsal", "drago-no-reviewer", "scratch")

WHAT = {
    "grid_records_final.csv": "fraction of the DP optimum each training task of a unit ended at, and the share "
                              "of its last 20 learner training episodes that reached half the optimum",
    "grid_records_coverage.csv": "world-model exact-match coverage per room after each stage",
    "grid_records_zero_shot.csv": "zero-shot return (retained model + true reward) per stage and task, as a "
                                  "fraction of the DP optimum",
    "grid_records_transfers.csv": "each transfer case's few-shot return at equal learner episodes and at equal env "
                                  "steps, the mean over its learning curve and the mean of the curve's last tenth, "
                                  "as fractions of the DP optimum, and the learner episodes to half the optimum",
    "grid_records_components.csv": "per-component retention (drago eval components) of every task seen after each "
                                   "stage",
    "grid_records_swap.csv": "the swap test of every earlier task after each stage, returns as fractions of the DP "
                             "optimum",
}
#: The side studies' data files, written once they have records.
WHAT_REVIEWER = {"grid_reviewer_records_coverage.csv": "drago-no-rehearsal with its reviewer paid against a lowered "
                                                       "θ: world-model exact-match coverage per room after each stage"}
WHAT_REVIEWER_2X = {"grid_reviewer_2x_records_coverage.csv": "drago-no-rehearsal with its reviewer paid against a "
                                                             "lowered θ, and continual, both at twice the task budget: "
                                                             "world-model exact-match coverage per room after each "
                                                             "stage"}
WHAT_DENSE = {"grid_dense_records_transfers.csv": "the transfer cases with dense reward: few-shot return at equal "
                                                  "learner episodes and at equal env steps, the mean over the "
                                                  "learning curve and the mean of the curve's last tenth, as "
                                                  "fractions of the optimum, and the learner episodes to half the "
                                                  "optimum"}
#: The commands that make each study's records (run from the repository's root). Each study needs a folder of
#: its own: one folder cannot hold two runs of a method and seed with different settings.
STUDY = "drago study minigrid-cpu --seeds 1-3 --jobs 2 train.threads=1"
MAIN_STUDY = f"{STUDY} --methods {' '.join(DEFAULT_METHODS)} --out runs/study/grid"
# the reviewer study asks what the reviewer keeps, so its units are runs without transfer cases
REVIEWER_STUDY = (f"{STUDY} --methods drago-no-rehearsal method.reviewer.threshold_offset=3 --no-transfer "
                  f"--out runs/study/grid-reviewer")
# twice the task budget: the learner's and the reviewer's steps, and the learning rate's decay stretched to match
REVIEWER_2X_STUDY = (f"{STUDY} --methods drago-no-rehearsal continual method.reviewer.threshold_offset=3 "
                     f"train.steps_per_task=20000 train.reviewer_steps_per_task=10000 "
                     f"agent.tdmpc.lr_schedule_steps=20000 --no-transfer --out runs/study/grid-reviewer-2x")
DENSE_STUDY = (f"{STUDY} --methods drago continual replay scratch --transfer-reward dense --transfer-episodes 100 "
               f"--out runs/study/grid-dense")


def write_sources(units: list[dict], folder: Path, what_of: dict[str, str], study: str) -> Path:
    """The entries of ``what_of``'s data files in docs/data/sources.json: what, the commands, and the records'
    dates, commits and machines."""
    path = _docs / "data" / "sources.json"
    sources = json.loads(path.read_text())
    for name, what in what_of.items():
        sources[name] = {
            "what": f"The grid study from its records: {what}, per method and seed",
            "command": f".venv/bin/python docs/make_grid_results.py (records from {study} --records {folder})",
            "preset": "minigrid-cpu", "units": len(units),
            "date": sorted({u["provenance"]["recorded"][:10] for u in units}),
            "commit": sorted({str(u["provenance"]["commit"])[:7] for u in units}),
            "machine": sorted({f"{u['provenance']['cpu']}, torch {u['provenance']['torch']}, "
                               f"{u['provenance']['threads']} thread(s)" for u in units})}
    path.write_text(json.dumps(sources, indent=2, ensure_ascii=False) + "\n")
    return path


def write_data(units: list[dict]) -> list[Path]:
    out = []
    rows = [{"method": u["method"], "seed": u["seed"], "task": task, "fraction_of_optimal": frac,
             "late_training_success": u["late_success"].get(task)}
            for u in units for task, frac in u["final"].items()]
    out.append(_write("grid_records_final.csv", rows,
                      ("method", "seed", "task", "fraction_of_optimal", "late_training_success")))
    out.append(_write("grid_records_coverage.csv", *_coverage_rows(units, ("method", "seed"))))
    rows = [{"method": u["method"], "seed": u["seed"], "stage": stage, "task": task, "fraction": frac}
            for u in units for (stage, task), frac in sorted(u["zero_shot"].items())]
    out.append(_write("grid_records_zero_shot.csv", rows, ("method", "seed", "stage", "task", "fraction")))
    out.append(_write("grid_records_transfers.csv", _transfer_rows(units), TRANSFER_COLUMNS))
    rows = [{"method": u["method"], "seed": u["seed"], "stage": stage, "task": task, "component": name, "value": value}
            for u in units for (stage, task), values in sorted(u["components"].items())
            for name, value in values.items()]
    out.append(_write("grid_records_components.csv", rows, ("method", "seed", "stage", "task", "component", "value")))
    rows = [{"method": u["method"], "seed": u["seed"], "stage": stage, "task": task, **readings}
            for u in units for (stage, task), readings in sorted(u["swap"].items())]
    out.append(_write("grid_records_swap.csv", rows, ("method", "seed", "stage", "task", *SWAP_READINGS)))
    return out


TRANSFER_COLUMNS = ("method", "seed", "case", "reward", *TRANSFER_READINGS, "episodes_to_half")


def _transfer_rows(units: list[dict]) -> list[dict]:
    return [{"method": u["method"], "seed": u["seed"], "case": case, **readings}
            for u in units for case, readings in sorted(u["transfers"].items())]


def write_side_data(reviewer_units: list[dict], dense_units: list[dict], reviewer_2x_units: list[dict] = ()
                    ) -> list[Path]:
    """The data of the reviewer studies (their coverage, with the offset of θ each paid against) and of the dense
    transfers, each only once it has a record."""
    out = []
    for name, pool in (("grid_reviewer_records_coverage.csv", reviewer_units),
                       ("grid_reviewer_2x_records_coverage.csv", reviewer_2x_units)):
        if pool:
            out.append(_write(name, *_coverage_rows(pool, ("method", "threshold_offset", "seed"))))
    if dense_units:
        out.append(_write("grid_dense_records_transfers.csv", _transfer_rows(dense_units), TRANSFER_COLUMNS))
    return out


def _coverage_rows(units: list[dict], keys: tuple[str, ...]) -> tuple[list[dict], tuple[str, ...]]:
    """Each unit's coverage per stage and room, after the unit's ``keys``: (rows, columns)."""
    rows = [{**{key: u[key] for key in keys}, "stage": stage, "room": room, "accuracy": acc}
            for u in units for (stage, room), acc in sorted(u["coverage"].items())]
    return rows, (*keys, "stage", "room", "accuracy")


def _write(name: str, rows: list[dict], columns: tuple[str, ...]) -> Path:
    path = _docs / "data" / name
    handle = io.StringIO(newline="")
    writer = csv.DictWriter(handle, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    path.write_text(handle.getvalue())
    return path


def _old_rooms(u: dict) -> float | None:
    """Mean coverage of rooms 1-3 after the fourth task."""
    values = [u["coverage"].get((4, room)) for room in ROOMS[:3]]
    return None if None in values else float(np.mean(values))


def _earlier_tasks_at_end(u: dict, source: str, key: str) -> float | None:
    """A unit's mean reading over the tasks before its last stage, after that stage (rooms 1-3 after task 4)."""
    if not u["stage_tasks"]:
        return None
    last = max(u["stage_tasks"])
    values = [readings[key] for (stage, task), readings in u[source].items()
              if stage == last and task != u["stage_tasks"][last] and key in readings]
    return float(np.mean(values)) if values else None


def forgot_table(units: list[dict]) -> list[str]:
    """Which part forgot: each component's reading on the earlier tasks after the last stage, per method, mean
    over those tasks per seed, then mean ± std [95% CI] over seeds."""
    by = _by_method(units)
    methods = _ordered(by, FORGOT_METHODS)
    if not methods:
        return []
    lines = ["| part (earlier rooms after the last task) | " + " | ".join(f"`{m}`" for m in methods) + " |",
             "|---|" + "---|" * len(methods)]
    for source, key, what in FORGOT_ROWS:
        cells = [_fmt([v for v in (_earlier_tasks_at_end(u, source, key) for u in by[m]) if v is not None])
                 for m in methods]
        lines.append(f"| {what} | " + " | ".join(cells) + " |")
    return lines


def dense_table(units: list[dict]) -> list[str]:
    """Every method of the dense transfers on each reading, each unit's mean over its four cases first, then mean ±
    std [95% CI] over seeds; and how many of its cases ended learned (the curve's end at ≥ ``LEARNED`` of the
    optimum), in all and per seed."""
    by = _by_method(units)
    methods = _ordered(by, DENSE_METHODS)
    if not methods:
        return []
    lines = ["| method | seeds | " + " | ".join(what for _, what in DENSE_READINGS)
             + f" | cases ended learned (≥ {LEARNED:.2f}): all (per seed) |",
             "|---|---|" + "---|" * (len(DENSE_READINGS) + 1)]
    for method in methods:
        pool = by[method]
        cells = [_fmt([v for v in (_transfer_mean(u, reading, "dense") for u in pool) if v is not None])
                 for reading, _ in DENSE_READINGS]
        ends = [[t["curve_end"] for t in u["transfers"].values()
                 if t.get("reward") == "dense" and t.get("curve_end") is not None] for u in pool]
        learned = [sum(end >= LEARNED for end in unit_ends) for unit_ends in ends]
        cells.append(f"{sum(learned)} of {sum(map(len, ends))} ({' / '.join(map(str, learned))})")
        lines.append(f"| `{method}` | {', '.join(str(u['seed']) for u in pool)} | " + " | ".join(cells) + " |")
    return lines


def dense_cases_table(units: list[dict]) -> list[str]:
    """Where each dense case's learning curve ended, per method and seed: which test task a retained model helps
    with shows only case by case."""
    by = _by_method(units)
    methods = _ordered(by, DENSE_METHODS)
    cases = sorted({case for u in units for case, t in u["transfers"].items() if t.get("reward") == "dense"})
    if not cases:
        return []
    lines = ["| case | " + " | ".join(f"`{m}`" for m in methods) + " |", "|---|" + "---|" * len(methods)]
    for case in cases:
        cells = []
        for method in methods:
            ends = [(u["seed"], end) for u in by[method]
                    if (end := u["transfers"].get(case, {}).get("curve_end")) is not None]
            seeds = [seed for seed, _ in ends]
            named = ("" if seeds == list(DEFAULT_SEEDS)
                     else f"seed{'s' * (len(seeds) > 1)} {', '.join(map(str, seeds))}: ")
            cells.append((named + " / ".join(f"{end:.2f}" for _, end in ends)
                          + f", {sum(end >= LEARNED for _, end in ends)} of {len(ends)} learned") if ends else "–")
        lines.append(f"| {case} | " + " | ".join(cells) + " |")
    return lines


def _late_note(unit: dict, task: str) -> str:
    share = unit.get("late_success", {}).get(task)
    return "" if share is None else f" (last {LATE_EPISODES} training episodes: {share:.0%} reached half the optimum)"


def _ordered(by: dict[str, list[dict]], first: tuple[str, ...]) -> list[str]:
    """The methods with units in ``by``: those of ``first`` in its order, then any others by name."""
    return [m for m in first if by.get(m)] + sorted(set(by) - set(first))


def _by_method(units: list[dict]) -> dict[str, list[dict]]:
    """Each method's units in seed order, the order every table and verdict shows them in."""
    by = defaultdict(list)
    for u in sorted(units, key=lambda u: u["seed"]):
        by[u["method"]].append(u)
    return by


def _against(claim: str, method: str, mine: list[float], other: str, base: list[float],
             wanted: int = len(DEFAULT_SEEDS)) -> tuple[str, str, str]:
    """A claim that ``method`` scores higher than ``other``: confirmed only when the 95% CIs over seeds separate;
    pending until each side has at least two seeds (one seed has no CI)."""
    numbers = f"{method} {_fmt(mine)}; {other} {_fmt(base)}"
    if len(mine) < 2 or len(base) < 2:
        return claim, f"pending: {len(mine)} and {len(base)} of {wanted} seeds recorded", numbers
    low, high = _ci(mine)
    b_low, b_high = _ci(base)
    verdict, why = (("confirmed", "CIs separate") if low > b_high else
                    ("contradicted", "CIs separate the other way") if high < b_low else
                    ("not separated by the CIs", ""))
    if len(mine) < wanted or len(base) < wanted:  # a bootstrap CI over two seeds is their range: say it is early
        why = "; ".join(filter(None, (why, f"{len(mine)} and {len(base)} of {wanted} seeds")))
        verdict += " so far"
    return claim, f"{verdict} ({why})" if why else verdict, numbers


def _zero_shot_tests(u: dict) -> float | None:
    """Mean zero-shot return on the test tasks after the fourth task."""
    values = [u["zero_shot"].get((4, t)) for t in TEST_TASKS]
    return None if None in values else float(np.mean(values))


def _transfer_mean(u: dict, reading: str, reward: str) -> float | None:
    """Mean over a unit's transfer cases with ``reward`` of one reading; None unless all four cases have it."""
    values = [t.get(reading) for t in u["transfers"].values() if t.get("reward") == reward]
    return float(np.mean(values)) if len(values) == 4 and None not in values else None


def verdicts(units: list[dict], reviewer_units: list[dict] = (), dense_units: list[dict] = (),
             reviewer_2x_units: list[dict] = ()) -> list[tuple[str, str, str]]:
    """The paper's claims, each ``(claim, verdict, numbers)``: from the main study's ``units``, the reviewer
    study's (``drago-no-rehearsal`` paid against a lowered θ), the dense transfers' and the reviewer study at
    twice the task budget's (``drago-no-rehearsal`` against ``continual`` of the same budget)."""
    by = _by_method(units)
    rows = []
    for method in ("drago", "drago-no-rehearsal", "drago-no-reviewer"):
        claim = f"`{method}` learns every room (≥ {LEARNED:.2f} of the optimum at each task's end)"
        mine = by.get(method, [])
        if not mine:
            rows.append((claim, "pending: no seed recorded", ""))
            continue
        fails = [f"seed {u['seed']} {task} {frac:.2f}" + _late_note(u, task) for u in mine
                 for task, frac in u["final"].items() if frac is not None and frac < LEARNED]
        shown = "; ".join(f"seed {u['seed']}: " + " / ".join(f"{u['final'].get(r, float('nan')):.2f}" for r in ROOMS)
                          for u in mine)
        seeds = f" ({len(mine)} of {len(DEFAULT_SEEDS)} seeds)"
        verdict = ("holds" if not fails else "fails: " + ", ".join(fails)) + seeds
        rows.append((claim, verdict, shown))

    def values(pool: list[dict], reading) -> list[float]:
        return [v for v in (reading(u) for u in pool) if v is not None]

    base = values(by.get("continual", []), _old_rooms)
    retained = " (coverage of rooms 1-3 after task 4)"
    for method, claim in (("drago", "DRAGO keeps rooms 1-3 after room 4 better than `continual`"),
                          ("drago-no-rehearsal", "the reviewer alone retains more than `continual`"),
                          ("drago-no-reviewer", "rehearsal alone retains more than `continual`")):
        rows.append(_against(claim + retained, method, values(by.get(method, []), _old_rooms), "continual", base))
    def reviewer_rows(pool: list[dict], base: list[float], at: str = "", tag: str = "") -> None:
        """The reviewer alone, paid against each lowered θ in ``pool``, against ``continual``'s ``base``."""
        reviewers = [u for u in pool if u["method"] == "drago-no-rehearsal"]
        for offset in sorted({u["threshold_offset"] for u in reviewers}) or [None]:
            mine = [u for u in reviewers if u["threshold_offset"] == offset]
            paid = "a lowered θ" if offset is None else f"θ − {offset:g}"
            shown = ", ".join(filter(None, (None if offset is None else paid, tag)))
            rows.append(_against(f"the reviewer alone, paid against {paid}, retains more than `continual`{at}"
                                 + retained, f"drago-no-rehearsal ({shown})" if shown else "drago-no-rehearsal",
                                 values(mine, _old_rooms), f"continual ({tag})" if tag else "continual", base))

    reviewer_rows(reviewer_units, base)
    if reviewer_2x_units:
        steps = sorted({u["steps_per_task"] for u in reviewer_2x_units if u.get("steps_per_task")})
        budget = " or ".join(f"{s:,}" for s in steps) + " steps a task" if steps else "twice the task budget"
        reviewer_rows(reviewer_2x_units, values(_by_method(reviewer_2x_units).get("continual", []), _old_rooms),
                      at=f" at twice the task budget ({budget}, both)", tag="2×")
    rows.append(_against("a retained DRAGO model plans the test tasks better than `continual`'s (zero-shot, after "
                         "task 4)", "drago", values(by.get("drago", []), _zero_shot_tests), "continual",
                         values(by.get("continual", []), _zero_shot_tests)))
    dense = _by_method(dense_units)
    for reading, what in DENSE_READINGS:
        rows.append(_against(f"a retained DRAGO model learns the test tasks faster than `continual`'s (dense "
                             f"reward, {what}, mean of the four cases)", "drago",
                             values(dense.get("drago", []), lambda u: _transfer_mean(u, reading, "dense")),
                             "continual",
                             values(dense.get("continual", []), lambda u: _transfer_mean(u, reading, "dense"))))
    return rows


def _recorded_line(units: list[dict], planned: int, what: str) -> str:
    digests = sorted({u["digest"] for u in units})
    cpus = sorted({u["provenance"]["cpu"] for u in units})
    commits = sorted({str(u["provenance"]["commit"])[:7] for u in units})
    dates = sorted({u["provenance"]["recorded"][:10] for u in units})
    when = (f", protocol {', '.join(digests)}, recorded {' to '.join(dict.fromkeys((dates[0], dates[-1])))} on "
            f"{'; '.join(cpus)} at commit {', '.join(commits)}") if units else ""
    count = len({(u["method"], u["seed"], u["threshold_offset"]) for u in units})
    return f"**{count} of {planned} units recorded** ({what}){when}."


def section(units: list[dict], folder: Path, reviewer_units: list[dict] = (), reviewer_folder: Path | None = None,
            dense_units: list[dict] = (), dense_folder: Path | None = None, reviewer_2x_units: list[dict] = (),
            reviewer_2x_folder: Path | None = None) -> str:
    command = " ".join(["docs/make_grid_results.py --records", str(folder),
                        *(["--reviewer-records", str(reviewer_folder)] if reviewer_folder else []),
                        *(["--reviewer-2x-records", str(reviewer_2x_folder)] if reviewer_2x_folder else []),
                        *(["--dense-records", str(dense_folder)] if dense_folder else [])])
    lines = [f"Generated by `.venv/bin/python {command}` from the committed records; data in "
             f"`docs/data/grid_*records_*.csv`, the full report of the records in "
             f"[grid-report/report.md](grid-report/report.md)"
             + (", the reviewer study at twice the task budget's in "
                "[grid-reviewer-2x-report/report.md](grid-reviewer-2x-report/report.md)" if reviewer_2x_units else "")
             + (", the dense transfers' in [grid-dense-report/report.md](grid-dense-report/report.md)"
                if dense_units else "") + ".", "",
             "- **The main study**: " + _recorded_line(units, len(DEFAULT_METHODS) * len(DEFAULT_SEEDS),
                                                       "a unit: one `minigrid-cpu` run of a method and seed, its "
                                                       "four sparse transfer cases and every evaluation of its "
                                                       "checkpoints")
             + f" Made by `{MAIN_STUDY} --records {folder}`.",
             "- **Does the reviewer regain anything?** " + _recorded_line(
                 reviewer_units, len(DEFAULT_SEEDS), "`drago-no-rehearsal`, its reviewer paid against θ − 3; runs and "
                 "their evaluations, no transfer cases")
             + f" Made by `{REVIEWER_STUDY} --records {reviewer_folder or 'results/grid-reviewer'}`."
             + ("" if not reviewer_2x_units else " At twice the task budget, beside `continual` at the same budget: "
                + _recorded_line(reviewer_2x_units, 2 * len(DEFAULT_SEEDS), "`drago-no-rehearsal` paid against θ − 3 "
                                 "and `continual`")
                + f" Made by `{REVIEWER_2X_STUDY} --records {reviewer_2x_folder}`."),
             "- **Transfer that can learn**: " + _recorded_line(
                 dense_units, 4 * len(DEFAULT_SEEDS), "`drago`, `continual`, `replay` and `scratch`, the four "
                 "transfer cases with dense reward and 100 learner episodes")
             + f" Made by `{DENSE_STUDY} --records {dense_folder or 'results/grid-dense'}`.", "",
             "Each study continues from its records on any machine with the same command; `--status` gives the "
             "units and CPU-hours left. The dense transfers start from the main study's runs: copies of its "
             "finished run directories without their `transfer/` folders, put in the dense study's `--out`, are "
             "skipped as finished, so only the transfers run.", "",
             "| method | env steps of a run: learner + reviewer | " + " | ".join(f"seed {s}" for s in DEFAULT_SEEDS)
             + " |", "|---|---|" + "---|" * len(DEFAULT_SEEDS)]
    for method in DEFAULT_METHODS:
        budgets = sorted({u["env_steps"] for u in units if u["method"] == method and u["env_steps"]})
        cells = [" or ".join(f"{learner:,} + {reviewer:,}" for learner, reviewer in budgets) or "–"]
        for seed in DEFAULT_SEEDS:
            u = next((u for u in units if (u["method"], u["seed"]) == (method, seed)), None)
            cells.append("to do" if u is None else
                         "rooms " + " / ".join(f"{u['final'].get(r, float('nan')):.2f}" for r in ROOMS)
                         + f", {u['cpu_h']:.2f} CPU-h")
        lines.append(f"| `{method}` | " + " | ".join(cells) + " |")
    lines += ["", "Each seed's cell: the fraction of the DP optimum each room's task ended at, and the run's CPU hours "
              "(transfers and evaluations not included). The env steps are the run's four tasks together "
              "(`costs.csv` of its record): every learner has the same budget, and DRAGO's reviewer collects its "
              "own on tasks 2-4.", "",
              "| the paper's claim | verdict from the records | numbers (mean ± std [95% CI]) |", "|---|---|---|"]
    lines += [f"| {claim} | {verdict} | {numbers} |"
              for claim, verdict, numbers in verdicts(units, reviewer_units, dense_units, reviewer_2x_units)]
    lines += ["", "A claim is confirmed only where the 95% CIs over seeds separate; the transfer rows average each "
              "unit's four cases first."]
    dense = dense_table(dense_units)
    if dense:
        lines += ["", "**Transfer that can learn, every method**: the four test cases with dense reward and "
                  f"{max(u.get('transfer_episodes', 0) for u in dense_units)} learner episodes each, every reading a "
                  "fraction of the case's optimum, each unit's mean over its four cases, then mean ± std [95% CI] "
                  "over seeds; the curve's end is the mean of its last tenth of evaluations. Per case and seed in "
                  "[`grid_dense_records_transfers.csv`](data/grid_dense_records_transfers.csv); the curves in the "
                  "[dense transfers' report](grid-dense-report/report.md#transfer-learning-curves).", "", *dense,
                  "", f"Where each case's learning curve ended (the mean of its last tenth), seeds "
                  f"{' / '.join(map(str, DEFAULT_SEEDS))} unless named, and how many ended learned "
                  f"(≥ {LEARNED:.2f}):", "",
                  *dense_cases_table(dense_units)]
    if (_docs / SCREENSHOT).is_file():
        lines += ["", f"The top of the report of the main study's records as a new user gets it: drawn by "
                  f"`.venv/bin/python docs/make_report_screenshots.py --in-fresh-clone --only {SCREENSHOT}`, which "
                  f"clones the repository, sets the clone up with `scripts/setup.sh` and builds the report there from "
                  f"the committed records alone:", "",
                  f"![The top of the report of the grid study's records, built in a fresh clone]({SCREENSHOT})"]
    forgot = forgot_table(units)
    if forgot:
        lines += ["", "**Which part forgot** ([how each part is measured](evaluation.md#which-part-forgot-grid)): "
                  "each part's reading on the rooms before the last task, after it (rooms 1-3 after room 4), mean "
                  "over those rooms per seed, then over seeds. The heads' rows read each room's own heads, which no "
                  "later task trains; the returns are fractions of each room's DP optimum. Swap-test evaluations: "
                  + ", ".join(sorted({e for u in units for e in u["evaluations"] if e.startswith("components")}))
                  + ".", "", *forgot]
    return "\n".join(lines)


def _build_report_into(target: Path, folders: list[Path]) -> None:
    """report.md and its figures only: the site renders the Markdown page, and a report.html beside it would be
    a second page of the same name."""
    import shutil
    import tempfile

    from drago.report import build_report

    shutil.rmtree(target, ignore_errors=True)
    target.mkdir()
    with tempfile.TemporaryDirectory() as scratch:
        build_report(folders, scratch)
        for path in sorted(Path(scratch).iterdir()):
            if path.suffix in (".md", ".png"):
                shutil.copy(path, target / path.name)
                print(f"wrote {target / path.name}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=Path, default=Path("results/grid"), help="the main study's records")
    parser.add_argument("--reviewer-records", type=Path, default=Path("results/grid-reviewer"),
                        help="the records of drago-no-rehearsal paid against a lowered θ (left out if absent)")
    parser.add_argument("--reviewer-2x-records", type=Path, default=Path("results/grid-reviewer-2x"),
                        help="the records of drago-no-rehearsal and continual at twice the task budget (left out if "
                             "absent)")
    parser.add_argument("--dense-records", type=Path, default=Path("results/grid-dense"),
                        help="the records of the dense-reward transfers (left out if absent)")
    parser.add_argument("--preset", default="minigrid-cpu", help="the study's preset; records of others are left out")
    parser.add_argument("--docs", type=Path, default=DOCS, help="the docs folder to write into (default: this one)")
    args = parser.parse_args()
    global _docs
    _docs = args.docs.resolve()
    os.chdir(ROOT)  # records are named by their path from the repository's root, on every machine
    folder = args.records
    units = load(folder, args.preset)
    reviewer_folder = args.reviewer_records if args.reviewer_records.is_dir() else None
    dense_folder = args.dense_records if args.dense_records.is_dir() else None
    reviewer_2x_folder = args.reviewer_2x_records if args.reviewer_2x_records.is_dir() else None
    reviewer_units = load(reviewer_folder, args.preset) if reviewer_folder else []
    reviewer_2x_units = load(reviewer_2x_folder, args.preset) if reviewer_2x_folder else []
    dense_units = load(dense_folder, args.preset) if dense_folder else []
    written = [*write_data(units), write_sources(units, folder, WHAT, MAIN_STUDY),
               *write_side_data(reviewer_units, dense_units, reviewer_2x_units)]
    if reviewer_units:
        written.append(write_sources(reviewer_units, reviewer_folder, WHAT_REVIEWER, REVIEWER_STUDY))
    if reviewer_2x_units:
        written.append(write_sources(reviewer_2x_units, reviewer_2x_folder, WHAT_REVIEWER_2X, REVIEWER_2X_STUDY))
    if dense_units:
        written.append(write_sources(dense_units, dense_folder, WHAT_DENSE, DENSE_STUDY))
    for path in written:
        print(f"wrote {path}")
    if units:
        # the reviewer study's runs are other runs of one method, reported beside the main study's under their own
        # label; the dense transfers hang off copies of the main study's runs, so they get a report of their own
        _build_report_into(_docs / "grid-report", [folder, *([reviewer_folder] if reviewer_units else [])])
    if reviewer_2x_units:  # its continual is not the main study's: a report of its own keeps the two apart
        _build_report_into(_docs / "grid-reviewer-2x-report", [reviewer_2x_folder])
    if dense_units:
        _build_report_into(_docs / "grid-dense-report", [dense_folder])
    page = _docs / "results.md"
    text = page.read_text()
    if START not in text or END not in text:
        print(f"{page} has no {START} ... {END} markers", file=sys.stderr)
        return 1
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    body = section(units, folder, reviewer_units, reviewer_folder, dense_units, dense_folder, reviewer_2x_units,
                   reviewer_2x_folder)
    page.write_text(f"{head}{START}\n{body}\n{END}{tail}")
    print(f"wrote {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
