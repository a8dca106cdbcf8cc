"""Regenerate the grid study's section of the results page from the committed records.

    .venv/bin/python docs/make_grid_results.py [--records results/grid] [--preset minigrid-cpu]

Reads every record in the folder (``drago study --records results/grid``), writes the per-unit numbers the
section shows into ``docs/data/grid_records_*.csv``, builds the report of the records into
``docs/grid-report/`` (report.md and its figures), and rewrites the part of ``docs/results.md`` between the
markers ``<!-- grid-records:start -->`` and ``<!-- grid-records:end -->``: what is recorded and what is left,
and the paper's claims, each with its verdict from the records with 95% CIs, or the seeds it still waits for.
Nothing else is read: no run directories, no checkpoints. The same records give the same files.
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
        transfers = {}
        for name, text in files.items():
            if name.startswith("transfer/") and name.endswith("/summary.json") and name.count("/") == 2:
                block = json.loads(text).get("transfer") or {}
                point = (block.get("few_shot") or {}).get("equal_episodes") or {}
                transfers[name.split("/")[1]] = point.get("fraction_of_optimal")
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
        units.append({"path": path,
                      "method": record["unit"]["method"], "seed": record["unit"]["seed"],
                      "digest": record["protocol"]["digest"], "provenance": record["provenance"],
                      "final": {t["name"]: t["fraction_of_optimal"] for t in summary["tasks"]},
                      "cpu_h": sum(float(t.get("cpu_time_s") or 0) for t in summary["tasks"]) / 3600,
                      "coverage": {(int(r["stage"]), r["room"]): float(r["accuracy"]) for r in coverage},
                      "zero_shot": {(int(r["stage"]), r["task"]): float(r["fraction"]) for r in zero
                                    if r.get("fraction") not in (None, "")},
                      "transfers": transfers, "components": dict(components), "swap": swap,
                      "stage_tasks": stage_tasks,
                      "evaluations": record["protocol"].get("evaluations", [])})
    return units


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
#: The methods of the "which part forgot" table, in the order the issue names them first.
FORGOT_METHODS = ("drago", "continual", "ewc", "replay", "drago-no-rehearsal", "drago-no-reviewer", "scratch")

WHAT = {
    "grid_records_final.csv": "fraction of the DP optimum each training task of a unit ended at",
    "grid_records_coverage.csv": "world-model exact-match coverage per room after each stage",
    "grid_records_zero_shot.csv": "zero-shot return (retained model + true reward) per stage and task, as a "
                                  "fraction of the DP optimum",
    "grid_records_transfers.csv": "few-shot return of each transfer case after 20 learner episodes, as a fraction "
                                  "of the DP optimum",
    "grid_records_components.csv": "per-component retention (drago eval components) of every task seen after each "
                                   "stage",
    "grid_records_swap.csv": "the swap test of every earlier task after each stage, returns as fractions of the DP "
                             "optimum",
}


def write_sources(units: list[dict], folder: Path) -> Path:
    """The data files' entries in docs/data/sources.json: what, the command, and the records' dates, commits
    and machines."""
    path = _docs / "data" / "sources.json"
    sources = json.loads(path.read_text())
    for name, what in WHAT.items():
        sources[name] = {
            "what": f"The grid study from its records: {what}, per method and seed",
            "command": f".venv/bin/python docs/make_grid_results.py --records {folder} (from drago study --jobs 2 "
                       f"--records {folder})",
            "preset": "minigrid-cpu", "units": len(units),
            "date": sorted({u["provenance"]["recorded"][:10] for u in units}),
            "commit": sorted({str(u["provenance"]["commit"])[:7] for u in units}),
            "machine": sorted({f"{u['provenance']['cpu']}, torch {u['provenance']['torch']}, "
                               f"{u['provenance']['threads']} thread(s)" for u in units})}
    path.write_text(json.dumps(sources, indent=2, ensure_ascii=False) + "\n")
    return path


def write_data(units: list[dict]) -> list[Path]:
    out = []
    rows = [{"method": u["method"], "seed": u["seed"], "task": task, "fraction_of_optimal": frac}
            for u in units for task, frac in u["final"].items()]
    out.append(_write("grid_records_final.csv", rows, ("method", "seed", "task", "fraction_of_optimal")))
    rows = [{"method": u["method"], "seed": u["seed"], "stage": stage, "room": room, "accuracy": acc}
            for u in units for (stage, room), acc in sorted(u["coverage"].items())]
    out.append(_write("grid_records_coverage.csv", rows, ("method", "seed", "stage", "room", "accuracy")))
    rows = [{"method": u["method"], "seed": u["seed"], "stage": stage, "task": task, "fraction": frac}
            for u in units for (stage, task), frac in sorted(u["zero_shot"].items())]
    out.append(_write("grid_records_zero_shot.csv", rows, ("method", "seed", "stage", "task", "fraction")))
    rows = [{"method": u["method"], "seed": u["seed"], "case": case, "fraction_equal_episodes": frac}
            for u in units for case, frac in sorted(u["transfers"].items())]
    out.append(_write("grid_records_transfers.csv", rows, ("method", "seed", "case", "fraction_equal_episodes")))
    rows = [{"method": u["method"], "seed": u["seed"], "stage": stage, "task": task, "component": name, "value": value}
            for u in units for (stage, task), values in sorted(u["components"].items())
            for name, value in values.items()]
    out.append(_write("grid_records_components.csv", rows, ("method", "seed", "stage", "task", "component", "value")))
    rows = [{"method": u["method"], "seed": u["seed"], "stage": stage, "task": task, **readings}
            for u in units for (stage, task), readings in sorted(u["swap"].items())]
    out.append(_write("grid_records_swap.csv", rows, ("method", "seed", "stage", "task", *SWAP_READINGS)))
    return out


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
    by = defaultdict(list)
    for u in units:
        by[u["method"]].append(u)
    methods = [m for m in FORGOT_METHODS if by.get(m)] + sorted(set(by) - set(FORGOT_METHODS))
    if not methods:
        return []
    lines = ["| part (earlier rooms after the last task) | " + " | ".join(f"`{m}`" for m in methods) + " |",
             "|---|" + "---|" * len(methods)]
    for source, key, what in FORGOT_ROWS:
        cells = [_fmt([v for v in (_earlier_tasks_at_end(u, source, key) for u in by[m]) if v is not None])
                 for m in methods]
        lines.append(f"| {what} | " + " | ".join(cells) + " |")
    return lines


def verdicts(units: list[dict]) -> list[tuple[str, str, str]]:
    by = defaultdict(list)
    for u in units:
        by[u["method"]].append(u)
    rows = []
    # DRAGO learns every room
    for method in ("drago", "drago-no-rehearsal", "drago-no-reviewer"):
        mine = sorted(by.get(method, []), key=lambda u: u["seed"])
        if not mine:
            rows.append((f"`{method}` learns every room (≥ {LEARNED:.2f} of the optimum at each task's end)",
                         "pending: no seed recorded", ""))
            continue
        fails = [f"seed {u['seed']} {task} {frac:.2f}" for u in mine for task, frac in u["final"].items()
                 if frac is not None and frac < LEARNED]
        shown = "; ".join(f"seed {u['seed']}: " + " / ".join(f"{u['final'].get(r, float('nan')):.2f}" for r in ROOMS)
                          for u in mine)
        seeds = f"{len(mine)} of {len(DEFAULT_SEEDS)} seeds"
        verdict = ("holds" if not fails else "fails: " + ", ".join(fails)) + f" ({seeds})"
        rows.append((f"`{method}` learns every room (≥ {LEARNED:.2f} of the optimum at each task's end)", verdict,
                     shown))
    # retention against continual, and each ablation against continual
    base = [v for v in (_old_rooms(u) for u in by.get("continual", [])) if v is not None]
    for method, claim in (("drago", "DRAGO keeps rooms 1-3 after room 4 better than `continual`"),
                          ("drago-no-rehearsal", "the reviewer alone retains more than `continual`"),
                          ("drago-no-reviewer", "rehearsal alone retains more than `continual`")):
        mine = [v for v in (_old_rooms(u) for u in by.get(method, [])) if v is not None]
        if len(mine) < 2 or len(base) < 2:
            rows.append((claim + " (coverage of rooms 1-3 after task 4)",
                         f"pending: {len(mine)} and {len(base)} of {len(DEFAULT_SEEDS)} seeds recorded",
                         f"{method} {_fmt(mine)}; continual {_fmt(base)}"))
            continue
        low, high = _ci(mine)
        b_low, b_high = _ci(base)
        verdict = ("confirmed (CIs separate)" if low > b_high else
                   "contradicted (CIs separate the other way)" if high < b_low else "not separated by the CIs")
        rows.append((claim + " (coverage of rooms 1-3 after task 4)", verdict,
                     f"{method} {_fmt(mine)}; continual {_fmt(base)}"))
    # zero-shot planning on the test tasks
    tests = ("room1to2", "room1to3", "room3to4")

    def zero(u: dict) -> float | None:
        values = [u["zero_shot"].get((4, t)) for t in tests]
        return None if None in values else float(np.mean(values))

    mine = [v for v in (zero(u) for u in by.get("drago", [])) if v is not None]
    base = [v for v in (zero(u) for u in by.get("continual", [])) if v is not None]
    claim = "a retained DRAGO model plans the test tasks better than `continual`'s (zero-shot, after task 4)"
    if len(mine) < 2 or len(base) < 2:
        rows.append((claim, f"pending: {len(mine)} and {len(base)} of {len(DEFAULT_SEEDS)} seeds recorded",
                     f"drago {_fmt(mine)}; continual {_fmt(base)}"))
    else:
        low, high = _ci(mine)
        b_low, b_high = _ci(base)
        verdict = ("confirmed (CIs separate)" if low > b_high else
                   "contradicted (CIs separate the other way)" if high < b_low else "not separated by the CIs")
        rows.append((claim, verdict, f"drago {_fmt(mine)}; continual {_fmt(base)}"))
    return rows


def section(units: list[dict], folder: Path) -> str:
    planned = len(DEFAULT_METHODS) * len(DEFAULT_SEEDS)
    recorded = sorted({(u["method"], u["seed"]) for u in units})
    digests = sorted({u["digest"] for u in units})
    cpus = sorted({u["provenance"]["cpu"] for u in units})
    commits = sorted({str(u["provenance"]["commit"])[:7] for u in units})
    dates = sorted(u["provenance"]["recorded"][:10] for u in units)
    lines = [f"Generated by `.venv/bin/python docs/make_grid_results.py --records {folder}` from the committed "
             f"records; data in `docs/data/grid_records_*.csv`, the full report of the records in "
             f"[grid-report/report.md](grid-report/report.md).", "",
             f"**{len(recorded)} of {planned} units recorded** (a unit: one `minigrid-cpu` run of a method and "
             f"seed, its four transfer cases and every evaluation of its checkpoints), protocol "
             f"{', '.join(digests) or '–'}, recorded {dates[0] if dates else '–'} to {dates[-1] if dates else '–'} "
             f"on {'; '.join(cpus) or '–'} at commit {', '.join(commits) or '–'}. The study continues with "
             f"`drago study --jobs 2 --records {folder}`; `--status` gives the units and CPU-hours left.", "",
             "| method | " + " | ".join(f"seed {s}" for s in DEFAULT_SEEDS) + " |",
             "|---|" + "---|" * len(DEFAULT_SEEDS)]
    for method in DEFAULT_METHODS:
        cells = []
        for seed in DEFAULT_SEEDS:
            u = next((u for u in units if (u["method"], u["seed"]) == (method, seed)), None)
            cells.append("to do" if u is None else
                         "rooms " + " / ".join(f"{u['final'].get(r, float('nan')):.2f}" for r in ROOMS)
                         + f", {u['cpu_h']:.2f} CPU-h")
        lines.append(f"| `{method}` | " + " | ".join(cells) + " |")
    lines += ["", "Each cell: the fraction of the DP optimum each room's task ended at, and the run's CPU hours "
              "(transfers and evaluations not included).", "",
              "| the paper's claim | verdict from the records | numbers (mean ± std [95% CI]) |", "|---|---|---|"]
    lines += [f"| {claim} | {verdict} | {numbers} |" for claim, verdict, numbers in verdicts(units)]
    forgot = forgot_table(units)
    if forgot:
        lines += ["", "**Which part forgot** ([how each part is measured](evaluation.md#which-part-forgot-grid)): "
                  "each part's reading on the rooms before the last task, after it (rooms 1-3 after room 4), mean "
                  "over those rooms per seed, then over seeds. The heads' rows read each room's own heads, which no "
                  "later task trains; the returns are fractions of each room's DP optimum. Swap-test evaluations: "
                  + ", ".join(sorted({e for u in units for e in u["evaluations"] if e.startswith("components")}))
                  + ".", "", *forgot]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=Path, default=Path("results/grid"))
    parser.add_argument("--preset", default="minigrid-cpu", help="the study's preset; records of others are left out")
    parser.add_argument("--docs", type=Path, default=DOCS, help="the docs folder to write into (default: this one)")
    args = parser.parse_args()
    global _docs
    _docs = args.docs.resolve()
    os.chdir(ROOT)  # records are named by their path from the repository's root, on every machine
    folder = args.records
    units = load(folder, args.preset)
    for path in [*write_data(units), write_sources(units, folder)]:
        print(f"wrote {path}")
    if units:
        import shutil
        import tempfile

        from drago.report import build_report

        # report.md and its figures only: the site renders the Markdown page, and a report.html beside it would
        # be a second page of the same name.
        target = _docs / "grid-report"
        shutil.rmtree(target, ignore_errors=True)
        target.mkdir()
        with tempfile.TemporaryDirectory() as scratch:
            build_report([folder], scratch)
            for path in sorted(Path(scratch).iterdir()):
                if path.suffix in (".md", ".png"):
                    shutil.copy(path, target / path.name)
                    print(f"wrote {target / path.name}")
    page = _docs / "results.md"
    text = page.read_text()
    if START not in text or END not in text:
        print(f"{page} has no {START} ... {END} markers", file=sys.stderr)
        return 1
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    page.write_text(f"{head}{START}\n{section(units, folder)}\n{END}{tail}")
    print(f"wrote {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
