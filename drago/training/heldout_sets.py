"""Held-out sets of DeepMind Control tasks: transitions of each task's final learner, recorded at the task's
end and never trained on, on which every later world model is scored (:mod:`drago.eval.heldout`)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from drago.config import Config
from drago.envs import exact_world, make_env
from drago.envs.episodes import run_episode
from drago.training.pre_rollout import load_learner
from drago.training.rundir import atomic_write, heldout_path, task_checkpoint_path
from drago.seeding import seeded_torch_rng, task_seed

# Seed purposes of drago.training.seeding.task_seed (0-3 are the training's own streams).
ENV_SEED_PURPOSE = 4
TORCH_SEED_PURPOSE = 5


class HeldoutSet(NamedTuple):
    """Transitions of one task's held-out set, float32, one row per transition."""

    obs: np.ndarray
    action: np.ndarray
    next_obs: np.ndarray
    reward: np.ndarray


def load_heldout(path: str | Path) -> HeldoutSet:
    with np.load(path) as data:
        return HeldoutSet(data["obs"], data["action"], data["next_obs"], data["reward"])


def record_heldout(checkpoint: str | Path, out: str | Path, device: Any = "cpu") -> Path:
    """Record the held-out set of a finished task from its task checkpoint and save it to ``out``.

    The checkpoint's learner (its heads and world model, planning as at the end of its task) runs
    :func:`record_transitions`; the trainer records the same set from the live learner, so both give
    the same file.

    Raises:
        drago.training.checkpoint.CheckpointError: unusable checkpoint.
    """
    saved = load_learner(checkpoint, device)
    return record_transitions(saved.agent, saved.steps, saved.config, saved.task_index, out, device)


def record_transitions(agent: Any, steps: int, cfg: Config, task_index: int, out: str | Path,
                       device: Any = "cpu") -> Path:
    """Record ``cfg.train.heldout_episodes`` eval-mode episodes of ``agent`` on task ``task_index`` of ``cfg``.

    The episodes (of the run's episode length) run on a new env of the task reset with a seed of its
    own, and the planner draws from a torch stream of its own, so nothing the training uses moves.

    Args:
        agent: the task's final learner (:class:`~drago.agent.agent.Agent`).
        steps: the task's step counter at its end (the learner's planning-horizon schedule).
        cfg: the run's config.
        task_index: 0-based position of the task in ``cfg.env.tasks``.
        out: the ``.npz`` file to write (atomically).
        device: the agent's torch device.
    """
    if cfg.train.heldout_episodes <= 0:
        raise ValueError(f"train.heldout_episodes is {cfg.train.heldout_episodes}: no held-out episodes to record")
    env = make_env(cfg.env.domain, cfg.env.tasks[task_index], cfg.env.dense_reward,
                   action_repeat=cfg.env.action_repeat)
    env.reset(seed=task_seed(cfg.train.seed, task_index, ENV_SEED_PURPOSE))
    episodes = []
    with seeded_torch_rng(task_seed(cfg.train.seed, task_index, TORCH_SEED_PURPOSE), device):
        for _ in range(cfg.train.heldout_episodes):
            episodes.append(run_episode(env, cfg.env.episode_length, lambda obs, t: agent.act(
                obs, steps, eval_mode=True, first_step=t == 0)))
    arrays = {"obs": np.concatenate([e.obs[:-1] for e in episodes]),
              "action": np.concatenate([e.actions for e in episodes]),
              "next_obs": np.concatenate([e.obs[1:] for e in episodes]),
              "reward": np.concatenate([e.rewards for e in episodes])}
    return atomic_write(out, lambda handle: np.savez(handle, **arrays))


class HeldoutRecorder:
    """The trainer's task-end hook that records each DeepMind Control task's held-out set.

    Called with the task's final learner, it records the set from it; called for a task finished before
    this process started (``learner`` None), it records the set from the task's checkpoint if the file is
    missing: a run that crashed in between, or one older than held-out sets.
    """

    def __init__(self, cfg: Config, run_dir: Path, device: Any, log: Callable[[str], None]):
        self.cfg, self.run_dir, self.device, self.log = cfg, Path(run_dir), device, log

    def __call__(self, index: int, learner: Any | None, step: int, buffers: Any = None) -> None:
        cfg = self.cfg
        path = heldout_path(self.run_dir, index + 1, cfg.env.tasks[index])
        if learner is None and path.exists():
            return
        if learner is None:
            record_heldout(task_checkpoint_path(self.run_dir, cfg.env.tasks, index + 1), path, self.device)
        else:
            record_transitions(learner, step, cfg, index, path, self.device)
        self.log(f"[{cfg.env.tasks[index]}] held-out set: {cfg.train.heldout_episodes} eval-mode episodes "
                 f"of the final learner -> {path.relative_to(self.run_dir)}")

    @staticmethod
    def wanted(cfg: Config) -> bool:
        return exact_world(cfg.env.domain) is None and cfg.train.heldout_episodes > 0
