"""Where each agent went on the grid: per task, the visits of every cell by the learner, by DRAGO's reviewer
and by a uniformly random agent given the reviewer's number of steps (docs: Evaluation, where the reviewer goes).

The counts come from the task's replay buffers at its end, which hold every episode of the task (their
capacity is the task's budget), so recording needs no state of its own and a resumed task counts exactly
what an uninterrupted one does. The random agent is the reference a reviewer must beat to be said to
seek anything: it plays the same task's environment with uniform actions on a stream of its own.

``RUN_DIR/visitation.csv`` has one row per (task, agent, cell) with at least one visit: ``stage`` (1-based),
``task``, ``agent`` (``learner``, ``reviewer``, ``random``), ``x``, ``y``, ``visits``. A visit is a step
taken from the cell (the L states of an episode that precede an action).
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from drago.agent.agent import random_action
from drago.agent.buffer import EpisodeReplay
from drago.config import Config
from drago.envs import env_spec, exact_world, make_env
from drago.envs.fourrooms import SIZE
from drago.seeding import task_seed
from drago.training.rundir import VISITATION_FILE, write_rows_csv

__all__ = ["AGENTS", "FIELDS", "VisitationRecorder", "read_visitation", "visit_counts"]

AGENTS = ("learner", "reviewer", "random")
FIELDS = ("stage", "task", "agent", "x", "y", "visits")
_RANDOM_PURPOSE = 7  # task_seed purpose of the random agent's stream (training, evaluation and others use 0-6)


def visit_counts(observations: np.ndarray) -> np.ndarray:
    """(SIZE, SIZE) visits indexed [y, x] of grid observations (N, 3), decoded as the environment encodes them."""
    obs = np.asarray(observations, dtype=np.float64).reshape(-1, 3)
    x = np.clip(np.rint((obs[:, 0] + 1.0) * SIZE / 2.0), 0, SIZE - 1).astype(int)
    y = np.clip(np.rint((obs[:, 1] + 1.0) * SIZE / 2.0), 0, SIZE - 1).astype(int)
    counts = np.zeros((SIZE, SIZE), dtype=np.int64)
    np.add.at(counts, (y, x), 1)
    return counts


def _random_agent_states(cfg: Config, index: int, steps: int) -> np.ndarray:
    """``steps`` states of a uniformly random agent in task ``index``'s environment, whole episodes."""
    L = cfg.env.episode_length
    env = make_env(cfg.env.domain, cfg.env.tasks[index], cfg.env.dense_reward, action_repeat=cfg.env.action_repeat)
    rng = np.random.default_rng(task_seed(cfg.train.seed, index, _RANDOM_PURPOSE))
    action_dim = env_spec(cfg.env.domain).action_dim
    states = []
    for episode in range(-(-steps // L)):
        obs, _ = env.reset(seed=int(rng.integers(2**31)))
        for _ in range(L):
            states.append(obs)
            obs, _, terminated, truncated, _ = env.step(random_action(rng, action_dim, True, ()))
            if terminated or truncated:
                break
    env.close()
    return np.asarray(states[:steps], dtype=np.float32)


class VisitationRecorder:
    """The trainer's task-end hook that writes each grid task's visitation (see the module's docstring).

    A task finished before this process started (no buffers) keeps whatever rows the file has for it.
    """

    def __init__(self, cfg: Config, run_dir: Path, log: Callable[[str], None]):
        self.cfg, self.run_dir, self.log = cfg, Path(run_dir), log

    @staticmethod
    def wanted(cfg: Config) -> bool:
        return exact_world(cfg.env.domain) is not None

    def __call__(self, index: int, learner: Any | None, step: int,
                 buffers: Mapping[str, EpisodeReplay] | None = None) -> None:
        if not buffers:
            return
        stage, task = index + 1, self.cfg.env.tasks[index]
        maps = {name: visit_counts(buffer.stored_states().cpu().numpy()) for name, buffer in buffers.items()}
        # The random reference takes the reviewer's steps, or the learner's in a task without a reviewer.
        steps = int(maps["reviewer" if "reviewer" in maps else "learner"].sum())
        maps["random"] = visit_counts(_random_agent_states(self.cfg, index, steps))
        path = self.run_dir / VISITATION_FILE
        rows = [row for row in read_visitation(path) if int(row["stage"]) != stage]  # a redone task replaces its rows
        for name in (name for name in AGENTS if name in maps):
            visits = maps[name]
            rows += [{"stage": stage, "task": task, "agent": name, "x": int(x), "y": int(y), "visits": int(visits[y, x])}
                     for y, x in zip(*np.nonzero(visits))]
        write_rows_csv(rows, FIELDS, path)
        counted = ", ".join(f"{name} {int(maps[name].sum())}" for name in AGENTS if name in maps)
        self.log(f"[{task}] visitation ({counted} steps) -> {VISITATION_FILE}")


def read_visitation(path: str | Path) -> list[dict[str, str]]:
    """The rows of a ``visitation.csv`` (none when the file does not exist)."""
    path = Path(path)
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))
