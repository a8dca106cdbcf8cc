"""Environments and the task catalogue, behind one factory."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym

from drago.envs.tasks import (DMC_SEQUENCES, DMC_TASKS, DMC_TRANSFER_TASKS, GRID_SEQUENCES, GRID_TASKS, DmcTask,
                               DmcTransferTask, GridTask, get_grid_task)


@dataclass(frozen=True)
class EnvSpec:
    """What the agent needs to know about a domain."""

    domain: str
    obs_dim: int
    action_dim: int
    discrete: bool  # one-hot actions and a categorical planner


# The DMC sizes are checked against dm_control in tests/test_dmc.py; here they need no import of it.
DOMAIN_SPECS = {
    "minigrid": EnvSpec("minigrid", obs_dim=3, action_dim=3, discrete=True),
    "cheetah": EnvSpec("cheetah", obs_dim=17, action_dim=6, discrete=False),
    "walker": EnvSpec("walker", obs_dim=24, action_dim=6, discrete=False),
}
DOMAINS = tuple(DOMAIN_SPECS)


def available_tasks(domain: str) -> list[str]:
    """Task names of a domain, training tasks first."""
    if domain == "minigrid":
        return list(GRID_TASKS)
    if domain in DOMAIN_SPECS:
        return [name for name, task in DMC_TASKS.items() if task.domain == domain]
    raise ValueError(f"unknown domain '{domain}'; valid domains: {', '.join(DOMAIN_SPECS)}")


def task_descriptions(domain: str) -> list[tuple[str, str]]:
    """(task, one line) for every task of a domain, for `drago list`."""
    if domain == "minigrid":
        # The catalogue's description already names start and goal.
        return [(name, f"{t.description}; {'dense' if t.dense else 'sparse'} reward")
                for name, t in GRID_TASKS.items()]
    return [(name, f"{DMC_TASKS[name].description}; reward {DMC_TASKS[name].reward}")
            for name in available_tasks(domain)]


def env_spec(domain: str) -> EnvSpec:
    if domain not in DOMAIN_SPECS:
        raise ValueError(f"unknown domain '{domain}'; valid domains: {', '.join(DOMAIN_SPECS)}")
    return DOMAIN_SPECS[domain]


def make_env(domain: str, task: str, dense_reward: bool | None = None, render_mode: str | None = None,
             action_repeat: int | None = None, max_episode_steps: int | None = None) -> gym.Env:
    """Build the env of one task; seed it through ``reset(seed=...)``.

    Args:
        domain: minigrid, cheetah or walker.
        task: a task of that domain (see :func:`available_tasks`).
        dense_reward: grid only: override the task's reward type (None: the catalogue's).
        render_mode: ``"rgb_array"`` to allow ``env.render()``.
        action_repeat: simulator control steps per agent step, rewards summed (None: the domain's
            official value: grid 1, cheetah 4, walker 2).
        max_episode_steps: DMC only: agent steps after which ``truncated`` is reported (None: never; the
            trainer counts episode steps itself).
    """
    if domain == "minigrid":
        from drago.envs.fourrooms import FourRoomsEnv

        if action_repeat not in (None, 1):
            raise ValueError(f"the grid has no action repeat; got action_repeat={action_repeat}")
        return FourRoomsEnv(get_grid_task(task, dense=dense_reward), render_mode=render_mode)
    if domain in DOMAIN_SPECS:
        if task not in available_tasks(domain):
            raise ValueError(f"unknown task '{task}' for domain {domain}; valid tasks: "
                             + ", ".join(available_tasks(domain)))
        if dense_reward is not None:
            raise ValueError(f"dense_reward applies to the grid only, not to domain {domain}")
        from drago.envs.dmc import DMCEnv  # imports dm_control: only when a DMC env is built

        return DMCEnv(task, action_repeat=action_repeat, max_episode_steps=max_episode_steps, render_mode=render_mode)
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

__all__ = ["DMC_SEQUENCES", "DMC_TASKS", "DMC_TRANSFER_TASKS", "DOMAINS", "DmcTask", "DmcTransferTask", "EnvSpec",
           "GRID_SEQUENCES", "GRID_TASKS", "GridTask", "available_tasks", "env_spec", "make_env", "task_descriptions",
           "task_optimum"]
