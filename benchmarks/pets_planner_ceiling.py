"""The ceiling of a PETS agent on the grid: its own CEM planner with the true dynamics and the true reward.

A PETS transfer on the grid (paper Appendix E) learns a test task from a retained ensemble and a fresh reward
head. Whatever the model knows, the return is bounded by what the planner finds when model and reward are
exact. This benchmark puts the grid's transition table in place of the ensemble (every member predicts the
true next state with no variance) and the task's true reward in place of the head, and plays each task with
the planner of ``--preset`` (its horizon, sequences, rounds and elites; ``key=value`` overrides change them).

PETS has no value function: a sequence is worth its predicted reward over the horizon alone. The dense reward
is paid only inside the goal's quadrant, so a start outside it (every test task's) is worth 0 to every
sequence until one sampled sequence reaches the quadrant; CEM then has nothing to refit and plays its mode.

Episode e starts on the task's start cell facing heading e mod 4 (as the zero-shot evaluation does), so every
4 episodes average over the start headings as the DP optimum does; one episode can exceed that average.

    .venv/bin/python benchmarks/pets_planner_ceiling.py [--preset minigrid-pets-cpu] [--tasks room1to2 ...]
        [--episodes 8] [--csv out.csv] [key=value ...]

Not part of the test suite. It prints the date, the command and the commit; the CSV holds one row per task.
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from zero_shot_ceiling import commit  # noqa: E402

from drago.agent.factory import pets_config  # noqa: E402
from drago.agent.pets import cem  # noqa: E402
from drago.config import load_config  # noqa: E402
from drago.envs import GRID_TASKS, make_env, task_optimum  # noqa: E402
from drago.envs.grid_reward import true_reward  # noqa: E402
from drago.envs.tasks import get_grid_task  # noqa: E402
from drago.eval.zero_shot import true_dynamics  # noqa: E402
from drago.training.rundir import write_rows_csv  # noqa: E402

OBS_DIM = ACTION_DIM = 3
EPISODE_LENGTH = 100


class TrueDynamics(torch.nn.Module):
    """An ensemble whose every member predicts the true next state of the grid, with no variance."""

    obs_dim, action_dim, predict_reward = OBS_DIM, ACTION_DIM, False

    def __init__(self, members: int):
        super().__init__()
        self.members = members

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rows = obs.reshape(-1, OBS_DIM)
        delta = (true_dynamics(rows, action.reshape(-1, ACTION_DIM)) - rows).reshape(obs.shape)
        if delta.dim() == 2:
            delta = delta.unsqueeze(0).expand(self.members, -1, -1)
        # exp(-60 / 2) ~ 1e-13: the particles' Gaussian draws leave the predicted state where it is.
        return delta, torch.full_like(delta, -60.0)


def play(task_name: str, plan, members: int, episodes: int, seed: int) -> list[float]:
    task = get_grid_task(task_name, dense=True)
    model = TrueDynamics(members)
    env = make_env("minigrid", task_name, dense_reward=True)
    reward_of = lambda obs, action, next_obs: true_reward(task, obs, action, next_obs)  # noqa: E731
    returns = []
    for e in range(episodes):
        generator = torch.Generator().manual_seed(seed * 1000 + e)
        env.reset(seed=seed * 1000 + e)
        obs = env.unwrapped.set_state(task.start, e % 4)
        total = 0.0
        for _ in range(EPISODE_LENGTH):
            action = cem(model, torch.as_tensor(obs, dtype=torch.float32), plan, discrete=True, eval_mode=True,
                         generator=generator, state_bounds=(-1.0, 1.0),
                         known_reward=reward_of).action
            obs, reward, terminated, truncated, _ = env.step(action.numpy())
            total += float(reward)
            if terminated or truncated:
                break
        returns.append(total)
    return returns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="minigrid-pets-cpu")
    parser.add_argument("--tasks", nargs="+", default=list(GRID_TASKS), choices=list(GRID_TASKS))
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--csv", default=None, help="also write the table to this file")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="planner settings, e.g. agent.pets.horizon=25")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}")
    print(f"command: {' '.join([Path(sys.executable).name, *sys.argv])}")
    print(f"commit: {commit()}")

    cfg = load_config(args.preset, args.overrides, method="continual")
    settings = pets_config(cfg)
    plan = settings.plan
    setting = " ".join([args.preset, *args.overrides])
    rows = []
    for name in args.tasks:
        start = time.perf_counter()
        returns = play(name, plan, settings.members, args.episodes, args.seed)
        optimum = task_optimum("minigrid", name, True)
        mean = float(np.mean(returns))
        rows.append({"planner": setting, "horizon": plan.horizon, "population": plan.population,
                     "iterations": plan.iterations, "elites": plan.elites, "task": name, "reward": "dense",
                     "episodes": len(returns), "returns": " ".join(f"{r:.1f}" for r in returns),
                     "mean_return": round(mean, 2), "optimum": round(optimum, 2), "fraction": round(mean / optimum, 3),
                     "episodes_scoring_zero": sum(r == 0 for r in returns)})
        print(f"{name:<9} horizon {plan.horizon} x {plan.population} sequences x {plan.iterations} rounds: "
              f"{mean:6.1f} of {optimum:.1f} ({mean / optimum:.2f}); {rows[-1]['episodes_scoring_zero']} of "
              f"{len(returns)} episodes scored 0 ({time.perf_counter() - start:.0f} s)")
    if args.csv:
        write_rows_csv(rows, tuple(rows[0]), args.csv)


if __name__ == "__main__":
    main()
