"""Playing fixed-length episodes: the learner's, DRAGO's reviewer's, the evaluations', the held-out recordings'."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

#: How an episode begins: maps an env to its first observation (None: ``env.reset()``). A transfer's
#: pre-rollout (paper Appendix, DeepMind Control test tasks) is such a start; its steps are not part of the episode.
EpisodeStart = Callable[[Any], np.ndarray]


@dataclass
class Episode:
    obs: np.ndarray  # (L+1, obs_dim)
    actions: np.ndarray  # (L, act_dim)
    rewards: np.ndarray  # (L,)

    @property
    def ret(self) -> float:
        return float(self.rewards.sum())


def run_episodes(envs, length: int, choose_actions, start: EpisodeStart | None = None) -> list[Episode]:
    """Roll one fixed-length episode in each env, side by side; ``choose_actions(obs, t)`` maps the (E, n)
    observations of step t to (E, n_a) actions, so one planner call serves every episode."""
    obs = np.stack([env.reset()[0] if start is None else start(env) for env in envs]).astype(np.float32)
    observations, actions, rewards = [obs], [], []
    for t in range(length):
        action = np.asarray(choose_actions(obs, t), dtype=np.float32)
        steps = [env.step(a) for env, a in zip(envs, action)]
        obs = np.stack([step[0] for step in steps]).astype(np.float32)
        observations.append(obs)
        actions.append(action)
        rewards.append([step[1] for step in steps])
    observations, actions = np.stack(observations), np.stack(actions)
    rewards = np.asarray(rewards, dtype=np.float32)
    return [Episode(observations[:, e], actions[:, e], rewards[:, e]) for e in range(len(envs))]


def run_episode(env, length: int, choose_action, start: EpisodeStart | None = None) -> Episode:
    """One episode of :func:`run_episodes`; ``choose_action(obs, t)`` maps one observation to one action."""
    return run_episodes([env], length, lambda obs, t: np.asarray(choose_action(obs[0], t))[None], start)[0]
