"""Environments and the task catalogue, behind one factory."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym

from drago.envs.tasks import GRID_SEQUENCES, GRID_TASKS, GridTask, get_grid_task


@dataclass(frozen=True)
class EnvSpec:
    """What the agent needs to know about a domain."""

    domain: str
    obs_dim: int
    action_dim: int
    discrete: bool  # one-hot actions and a categorical planner


DOMAIN_SPECS = {"minigrid": EnvSpec("minigrid", obs_dim=3, action_dim=3, discrete=True)}


def available_tasks(domain: str) -> list[str]:
    """Task names of a domain, training tasks first."""
    if domain == "minigrid":
        return list(GRID_TASKS)
    raise ValueError(f"unknown domain '{domain}'; valid domains: {', '.join(DOMAIN_SPECS)}")


def env_spec(domain: str) -> EnvSpec:
    if domain not in DOMAIN_SPECS:
        raise ValueError(f"unknown domain '{domain}'; valid domains: {', '.join(DOMAIN_SPECS)}")
    return DOMAIN_SPECS[domain]


def make_env(domain: str, task: str, dense_reward: bool | None = None, render_mode: str | None = None) -> gym.Env:
    """Build the env of one task; seed it through ``reset(seed=...)``."""
    if domain == "minigrid":
        from drago.envs.fourrooms import FourRoomsEnv

        return FourRoomsEnv(get_grid_task(task, dense=dense_reward), render_mode=render_mode)
    raise ValueError(f"unknown domain '{domain}'; valid domains: {', '.join(DOMAIN_SPECS)}")


def task_optimum(domain: str, task: str, dense_reward: bool | None = None) -> float | None:
    """The exact optimal return of a task where one is known (grid: finite-horizon DP), else None."""
    if domain == "minigrid":
        from drago.envs.fourrooms import optimal_return

        return optimal_return(get_grid_task(task, dense=dense_reward))
    return None


# The official code's gymnasium id, so `gymnasium.make("MiniGrid-FourRooms-New", task="room2")` works.
gym.register(id="MiniGrid-FourRooms-New", entry_point="drago.envs.fourrooms:make_fourrooms",
             max_episode_steps=None)

__all__ = ["EnvSpec", "GRID_SEQUENCES", "GRID_TASKS", "GridTask", "available_tasks", "env_spec", "make_env",
           "task_optimum"]
