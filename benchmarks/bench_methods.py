"""What each continual method costs over `continual`: time per task and memory (issue "DRAGO", item 3).

Each method runs in its own process (so peak memory is its own) on a short two-task version of a
preset: task 1 to build what the method carries, then task 2, where the extra machinery of most
methods runs (DRAGO's reviewer, VAE and rehearsal; EWC's penalty; replay's old transitions). From
task 2's timing log it takes the median CPU seconds per training iteration after the seed phase (one
thread, so this is also the wall time of a process with a core to itself) and scales it to the
preset's full task budget. CPU seconds rather than wall time keep the ratios steady when other jobs
share the machine. Memory is task 2's peak resident set size and the size of the checkpoint handed
to the next task.

    .venv/bin/python benchmarks/bench_methods.py [--preset minigrid-cpu] [--threads 1] [--json out.json]

Not part of the test suite. Wall seconds are printed too; they mean something only on an idle machine.
The median is over the ten-odd iterations of a short task 2: on a loaded machine, methods that do
exactly `continual`'s work (scratch) came out up to 1.1x, so read smaller differences as noise.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

METHODS = ("continual", "scratch", "ewc", "curiosity", "replay", "pseudo-rehearsal", "drago",
           "drago-no-rehearsal", "drago-no-reviewer", "drago-single-agent")


def measure_one(preset: str, method: str, threads: int, steps: int, seed_steps: int) -> dict:
    """Train a two-task sequence in this process and return the costs of its second task."""
    from drago.config import load_config
    from drago.continual.base import Budget
    from drago.training.run import new_run

    full = load_config(preset, method=method)
    cfg = load_config(preset, [f"env.tasks=[{','.join(full.env.tasks[:2])}]",
                               f"train.steps_per_task={steps}", f"agent.seed_steps={seed_steps}",
                               "train.eval_episodes=1", f"train.eval_freq={steps}",
                               f"train.checkpoint_freq={steps}", "train.tensorboard=false",
                               f"train.threads={threads}"], method=method)
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        new_run(cfg, run_dir, progress=False).run()
        second = cfg.env.tasks[1]
        with open(run_dir / "timing.csv") as handle:
            rows = [r for r in csv.DictReader(handle) if r["task"] == second and float(r["update_s"]) > 0]
        summary = json.loads((run_dir / "summary.json").read_text())
        carried = (run_dir / summary["tasks"][0]["checkpoint"]).stat().st_size
    if not rows:
        raise SystemExit(f"no post-seed iteration in task 2 for {method}; raise --steps above --seed-steps")
    task2 = summary["tasks"][1]
    env_steps_per_iteration = task2["env_steps"] / task2["episodes"]
    iteration_cpu_s = statistics.median(float(r["cpu_s"]) for r in rows)
    iteration_wall_s = statistics.median(float(r["collect_s"]) + float(r["update_s"]) for r in rows)
    iterations_full_budget = Budget.from_config(full).max_steps * full.env.action_repeat / env_steps_per_iteration
    return {"method": method, "iterations_measured": len(rows), "iteration_cpu_s": iteration_cpu_s,
            "iteration_wall_s": iteration_wall_s, "env_steps_per_iteration": env_steps_per_iteration,
            "task_cpu_s_full_budget": iteration_cpu_s * iterations_full_budget,
            "peak_rss_mib": task2["peak_rss_mib"], "carried_checkpoint_kb": carried / 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="minigrid-cpu")
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--steps", type=int, default=2500, help="env steps per task of the short sequence")
    parser.add_argument("--seed-steps", type=int, default=1000)
    parser.add_argument("--json", default=None, help="also write the results to this file")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)  # child process: one method
    args = parser.parse_args()

    if args.one:
        print(json.dumps(measure_one(args.preset, args.one, args.threads, args.steps, args.seed_steps)))
        return

    results = []
    for method in args.methods:
        out = subprocess.run([sys.executable, __file__, "--one", method, "--preset", args.preset,
                              "--threads", str(args.threads), "--steps", str(args.steps),
                              "--seed-steps", str(args.seed_steps)], capture_output=True, text=True)
        if out.returncode != 0:
            raise SystemExit(f"{method} failed:\n{out.stderr.strip()}")
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(f"measured {method}", file=sys.stderr)

    base = next((r for r in results if r["method"] == "continual"), results[0])
    print(f"preset {args.preset}, {args.threads} thread(s); task-2 iterations after the seed phase, "
          f"CPU seconds scaled to the preset's full task budget")
    print(f"{'method':<20}{'CPU s/it':>9}{'wall s/it':>10}{'env steps/it':>13}{'CPU s/task':>11}{'x continual':>12}"
          f"{'peak RSS MiB':>13}{'x continual':>12}{'carried kB':>12}")
    for r in results:
        print(f"{r['method']:<20}{r['iteration_cpu_s']:>9.2f}{r['iteration_wall_s']:>10.2f}"
              f"{r['env_steps_per_iteration']:>13.0f}{r['task_cpu_s_full_budget']:>11.0f}"
              f"{r['task_cpu_s_full_budget'] / base['task_cpu_s_full_budget']:>12.2f}"
              f"{r['peak_rss_mib']:>13.0f}{r['peak_rss_mib'] / base['peak_rss_mib']:>12.2f}"
              f"{r['carried_checkpoint_kb']:>12.0f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"preset": args.preset, "threads": args.threads,
                                               "results": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
