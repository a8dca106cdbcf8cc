"""How the swap test's refit behaves under different budgets, on the checkpoints of finished grid runs.

The swap test (docs: Evaluation, "Which part forgot") refits an earlier task's saved heads over a later world
model and plans with them. That column means something only if the refit lands in the same place whatever its
own random batches: this benchmark refits every swap case of each run under several budgets (updates, and the
learning rate at the last update as a fraction of the agent's, 1 for a constant one), a few times each with
the swap test's own seeds, and writes one row per case and budget: the return of the saved heads under the
later model (moved), the refits' returns (mean, lowest, highest, each draw), all as fractions of the task's
DP optimum, and the CPU seconds of one refit.

    .venv/bin/python benchmarks/refit_budget.py RUN_DIR [RUN_DIR ...] [--budgets 200:1,1000:0.01]
        [--draws 3] [--out docs/data/refit_budget.csv] [--append] [--threads 1]

--append keeps the rows already in --out (another run or other budgets measured before).

Not part of the test suite. It prints the date, the command and the commit; the CSV holds the table only.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from drago.eval.components import load_run_stages, refit_heads
from drago.eval.coverage import task_room
from drago.training.rundir import write_rows_csv

COLUMNS = ("method", "seed", "stage", "task", "updates", "lr_decay", "moved", "refit_mean", "refit_min",
           "refit_max", "refits", "cpu_s_per_refit")
ROOT = Path(__file__).resolve().parents[1]


def commit() -> str:
    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def budgets(text: str) -> list[tuple[int, float]]:
    try:
        pairs = [item.split(":") for item in text.split(",")]
        return [(int(updates), float(decay)) for updates, decay in pairs]
    except ValueError:
        raise SystemExit(f"--budgets takes UPDATES:LR_DECAY pairs separated by commas (200:1,1000:0.01), got {text!r}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--budgets", type=budgets, default=budgets("200:1,1000:0.01"))
    parser.add_argument("--draws", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "data" / "refit_budget.csv")
    parser.add_argument("--append", action="store_true", help="keep the rows already in --out")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(f"# {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, commit {commit()}, "
          f"command: {' '.join(sys.argv)}", flush=True)
    rows = []
    if args.append and args.out.exists():
        with args.out.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
    for run in args.runs:
        stages = load_run_stages(run)
        cfg = stages.cfg
        for n in range(len(stages.checkpoints)):
            for k in range(n):
                if stages.heads[k] is None or task_room(stages.checkpoints[k].task) is None:
                    continue
                optimum = stages.optimum(k)
                moved = stages.planned_return(n, stages.heads[k], k) / optimum
                for updates, decay in args.budgets:
                    started, refits = time.process_time(), []
                    for seed in stages.refit_seeds(args.draws):
                        heads = refit_heads(stages.models[n], stages.heads[k], stages.probe(k),
                                            stages.agent_configs[n], updates=updates, seed=seed, lr_decay=decay)
                        refits.append(stages.planned_return(n, heads, k) / optimum)
                    row = {"method": cfg.method.name, "seed": cfg.train.seed,
                           "stage": stages.checkpoints[n].stage, "task": stages.checkpoints[k].task,
                           "updates": updates, "lr_decay": decay, "moved": round(moved, 3),
                           "refit_mean": round(float(np.mean(refits)), 3), "refit_min": round(min(refits), 3),
                           "refit_max": round(max(refits), 3), "refits": " ".join(f"{r:.3f}" for r in refits),
                           "cpu_s_per_refit": round((time.process_time() - started) / len(refits), 1)}
                    rows.append(row)
                    print("  ".join(f"{key}={row[key]}" for key in COLUMNS), flush=True)
                    write_rows_csv(rows, COLUMNS, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
