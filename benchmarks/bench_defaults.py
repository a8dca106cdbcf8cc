"""Today's default speed settings against the plain path (float32, eager, torch's tanh), in one process, alternating.

For each preset, DRAGO is set up at the start of task 2 twice (``bench_speed.task_two``): once with the
preset's settings resolved as a run on this machine would resolve them (``agent.tdmpc.precision=auto``,
``agent.tdmpc.compile=auto``, ``agent.tdmpc.fast_tanh=true``), once forced to ``float32``, ``false`` and ``false``, the
path whose cost matches the official code's. Each round then times one call of every component of each
form in turn (a planned action, a learner update, a full DRAGO gradient step), so both forms see the same
machine; the figures are medians over ``--rounds``, after ``--warmup`` calls of each (which also compile).

    .venv/bin/python benchmarks/bench_defaults.py [--presets minigrid minigrid-cpu] [--rounds 10] [--threads 2]
        [--csv out.csv]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_speed import components, task_two  # noqa: E402

from drago.agent.speed import resolve_speed, speed_summary  # noqa: E402
from drago.config import load_config  # noqa: E402
from drago.training.resources import keep_freed_memory  # noqa: E402
from drago.training.rundir import write_rows_csv  # noqa: E402

PLAIN = ["agent.tdmpc.precision=float32", "agent.tdmpc.compile=false", "agent.tdmpc.fast_tanh=false"]
TIMED = ("act", "update", "drago_step")


def build(preset: str, overrides: list[str]):
    cfg = load_config(preset, overrides, method="drago")
    cfg, notes = resolve_speed(cfg, torch.device(cfg.train.device))
    method, task = task_two(cfg, torch.device(cfg.train.device))
    return cfg, notes, components(method, task, cfg)


def bench(preset: str, rounds: int, warmup: int) -> list[list]:
    forms = {"default": build(preset, []), "plain": build(preset, PLAIN)}
    for name, (cfg, notes, _) in forms.items():
        print(f"{preset} {name}: {speed_summary(cfg.agent)}" + "".join(f"\n  {n}" for n in notes), flush=True)
    for _, _, parts in forms.values():
        for key in TIMED:
            for _ in range(warmup):
                parts[key][0]()
    samples = {(form, key): [] for form in forms for key in TIMED}
    for _ in range(rounds):
        for key in TIMED:
            for form, (_, _, parts) in forms.items():
                t0 = time.perf_counter()
                parts[key][0]()
                samples[(form, key)].append(time.perf_counter() - t0)
    rows = []
    for key in TIMED:
        default, plain = (1e3 * statistics.median(samples[(f, key)]) for f in ("default", "plain"))
        rows.append([preset, forms["default"][0].agent.tdmpc.mlp_dim, key, speed_summary(forms["default"][0].agent),
                     round(default, 2), round(plain, 2), round(plain / default, 3)])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["minigrid", "minigrid-cpu"])
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--csv", default=None, help="also write the table to this file")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    keep_freed_memory()
    print(f"torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}, "
          f"median of {args.rounds} alternating rounds")
    rows = [row for preset in args.presets for row in bench(preset, args.rounds, args.warmup)]
    header = ["preset", "width", "component", "default_settings", "default_ms", "plain_ms", "speedup"]
    print(f"{'preset':<14}{'width':>6}  {'component':<12}{'default ms':>12}{'plain ms':>11}{'speed-up':>10}")
    for r in rows:
        print(f"{r[0]:<14}{r[1]:>6}  {r[2]:<12}{r[4]:>12.2f}{r[5]:>11.2f}{r[6]:>9.2f}x")
    if args.csv:
        write_rows_csv([dict(zip(header, row)) for row in rows], tuple(header), args.csv)


if __name__ == "__main__":
    main()
