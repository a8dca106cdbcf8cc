"""The ceiling of the zero-shot evaluation: its planner with the true dynamics in place of a world model.

`drago.eval.zero_shot` plans with a run's world model and the task's true reward. What it can measure is
bounded by its planner: a model that is exactly right should turn into the DP optimum of every task. This
benchmark checks it on the four training rooms and the three transfer tasks, each read dense and sparse,
over a few seeds (episode e of a seed starts facing heading e mod 4, so 4 episodes average exactly over
the start headings, as the DP optimum does). It repeats the check at shorter lookaheads to show where the
ceiling breaks: at the agent's own horizons the goal of another room, or a sparse goal, is out of sight.
Each measurement is made with no random steps (epsilon 0: the planner alone, which should be exact) and
with the evaluation's default share of random steps (what the reported matrices are read against).

It then times a whole zero-shot matrix (4 stages x 7 tasks) of one run on one thread: a run given with
--run, or else a smoke run trained here with the minigrid-cpu world model's width (agent.tdmpc.mlp_dim=128),
whose models learned nothing but cost what a trained one costs to plan with.

    .venv/bin/python benchmarks/zero_shot_ceiling.py [--seeds 3] [--episodes 4] [--horizons 5,10,15,20,25,100]
        [--epsilons 0,0.05] [--out docs/data/zero_shot_ceiling.csv] [--run RUN_DIR | --no-matrix] [--threads 1]

Not part of the test suite. It prints the date, the command and the commit; the CSV holds the table only
(one row per task, reward, horizon and epsilon). Wall seconds mean something only on an idle machine.
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from drago.envs.fourrooms import optimal_returns
from drago.envs.tasks import get_grid_task
from drago.training.rundir import write_rows_csv
from drago.eval.zero_shot import (
    DEFAULT_EPISODES,
    DEFAULT_EPSILON,
    DEFAULT_HORIZON,
    GRID_TASKS_TRAINING,
    default_tasks,
    format_table,
    lattice_model,
    play,
    true_dynamics,
    zero_shot_matrix,
)

COLUMNS = ("task", "reward", "horizon", "epsilon", "optimum", "ceiling_mean", "ceiling_std", "fraction", "optimal_episodes",
           "seeds", "episodes", "wall_s")
ROOT = Path(__file__).resolve().parents[1]


def commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=ROOT, capture_output=True, text=True,
                               check=True).stdout.strip()
        return out + (" (with uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def measure(task_name: str, dense: bool, horizon: int, epsilon: float, seeds: int, episodes: int) -> dict:
    """The ceiling of one task and reading: per seed the mean over its episodes, then mean and std over seeds."""
    task = get_grid_task(task_name, dense=dense)
    per_heading = optimal_returns(task)
    optimum = float(per_heading.mean())
    model = lattice_model(true_dynamics)
    start = time.perf_counter()
    means, optimal = [], 0
    for seed in range(seeds):
        returns = play(model, task, episodes, seed, 0, horizon, epsilon)
        means.append(float(returns.mean()))
        # Episode e starts facing heading e mod 4: compare it with that heading's own optimum.
        optimal += sum(int(abs(r - per_heading[e % 4]) < 1e-9) for e, r in enumerate(returns.tolist()))
    wall = time.perf_counter() - start
    mean = statistics.fmean(means)
    return {"task": task_name, "reward": "dense" if dense else "sparse", "horizon": horizon, "epsilon": epsilon,
            "optimum": optimum,
            "ceiling_mean": mean, "ceiling_std": statistics.stdev(means) if seeds > 1 else 0.0,
            "fraction": mean / optimum, "optimal_episodes": optimal / (seeds * episodes), "seeds": seeds,
            "episodes": episodes, "wall_s": round(wall, 3)}


def smoke_run(where: Path) -> Path:
    """A smoke run with the minigrid-cpu world model's width, trained here (about half a minute)."""
    from drago.config import load_config
    from drago.training.run import new_run

    cfg = load_config("smoke", ["agent.tdmpc.mlp_dim=128", "train.tensorboard=false", "train.threads=1"],
                      method="continual")
    run_dir = where / "run"
    new_run(cfg, run_dir, progress=False).run()
    return run_dir


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=DEFAULT_EPISODES)
    parser.add_argument("--horizons", default=f"5,10,15,20,25,{DEFAULT_HORIZON}",
                        help="lookaheads to measure; the last is the one the table headlines")
    parser.add_argument("--epsilons", default=f"0,{DEFAULT_EPSILON:g}",
                        help="shares of random steps to measure; the last is the one the table headlines")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "data" / "zero_shot_ceiling.csv")
    parser.add_argument("--run", type=Path, help="time the matrix of this grid run instead of a smoke run")
    parser.add_argument("--no-matrix", action="store_true", help="skip timing a run's matrix")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    horizons = [int(h) for h in args.horizons.split(",")]
    epsilons = [float(e) for e in args.epsilons.split(",")]

    print(f"date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}")
    print(f"command: {' '.join([Path(sys.executable).name, *sys.argv])}")
    print(f"commit: {commit()}")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); seeds {args.seeds}, "
          f"episodes per seed {args.episodes}")
    # One-time costs (the grid's transition table) are paid before anything is timed.
    play(lattice_model(true_dynamics), get_grid_task("room1"), 1, 0, 0, 5, 0.0)

    tasks = default_tasks(GRID_TASKS_TRAINING)
    rows = [measure(t, dense, h, e, args.seeds, args.episodes)
            for e in epsilons for h in horizons for t in tasks for dense in (True, False)]
    write_rows_csv(rows, COLUMNS, args.out)

    headline, noise = horizons[-1], epsilons[-1]
    print(f"\nceiling at horizon {headline}, epsilon {noise:g} (mean +- std over seeds of the mean return of "
          f"{args.episodes} episodes)")
    print(f"{'task':<9} {'reward':<6} {'DP optimum':>10} {'ceiling':>16} {'fraction':>8} {'optimal eps':>11} "
          f"{'wall s':>7}")
    for r in rows:
        if r["horizon"] == headline and r["epsilon"] == noise:
            print(f"{r['task']:<9} {r['reward']:<6} {r['optimum']:>10.2f} "
                  f"{r['ceiling_mean']:>9.2f} +- {r['ceiling_std']:<4.2f} {r['fraction']:>8.3f} "
                  f"{r['optimal_episodes']:>11.2f} {r['wall_s']:>7.2f}")
    print("\nfraction of the DP optimum by lookahead (rows: epsilon and horizon)")
    labels = [f"{t}:{d[0]}" for t in tasks for d in ("dense", "sparse")]
    print(f"{'eps':>5} {'horizon':>7} " + " ".join(f"{label:>10}" for label in labels))
    for e in epsilons:
        for h in horizons:
            cells = [r["fraction"] for r in rows if r["horizon"] == h and r["epsilon"] == e]
            print(f"{e:>5g} {h:>7} " + " ".join(f"{c:>10.3f}" for c in cells))
    print(f"\nwrote {args.out}")

    if not args.no_matrix:
        with tempfile.TemporaryDirectory() as tmp:
            run_dir = args.run
            if run_dir is None:
                print("\ntraining a smoke run with agent.tdmpc.mlp_dim=128 to time a matrix ...")
                run_dir = smoke_run(Path(tmp))
            times, matrix = [], []
            for _ in range(2):
                start = time.perf_counter()
                matrix = zero_shot_matrix(run_dir, episodes=args.episodes, seed=0)
                times.append(time.perf_counter() - start)
            print(f"\nzero-shot matrix of {run_dir} ({len(matrix)} rows, {args.episodes} episodes each, "
                  f"horizon {DEFAULT_HORIZON}): {min(times):.2f} s on {torch.get_num_threads()} thread(s) "
                  f"(best of {len(times)}: {', '.join(f'{t:.2f}' for t in times)})")
            print("\n".join(format_table(matrix)))
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    sys.exit(main())
