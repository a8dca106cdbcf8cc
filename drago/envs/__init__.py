"""Environments and the task catalogue, behind one factory and a registry of domains.

A domain is data plus a factory (:class:`Domain`): its sizes, its tasks, how to build the env of a task.
The built-in domains (minigrid, cheetah, walker and the pendulum example) are registered like any
other; :func:`register_domain` adds yours, :func:`gym_domain` makes one from gymnasium envs, packages
add theirs through the ``drago.domains`` entry points, and ``dmc:DOMAIN`` names every stock dm_control
task. The functions below are thin lookups over the registry.
"""

from __future__ import annotations

import gymnasium as gym

from drago.envs.builtin import CHEETAH, GRID_DOMAIN, MINIGRID, WALKER
from drago.envs.domain import Domain, DomainError, EnvSpec
from drago.envs.gym_envs import FlatEnv, TransitionReward, gym_domain, reward_variant
from drago.envs.registry import (ENTRY_POINT_GROUP, PluginProblem, available_domains, domain_families, get_domain,
                                 is_domain, load_plugins, plugin_problems, register_domain, source_of,
                                 unregister_domain)
from drago.envs.tasks import (DMC_SEQUENCES, DMC_TASKS, DMC_TRANSFER_TASKS, GRID_SEQUENCES, GRID_TASKS, DmcTask,
                              DmcTransferTask, GridTask, get_grid_task)

#: The paper's three domains. Every registered domain is in :func:`available_domains`.
DOMAINS = ("minigrid", "cheetah", "walker")
#: Their sizes (kept for older callers; :func:`env_spec` answers for every domain).
DOMAIN_SPECS = {d.name: d.env_spec() for d in (MINIGRID, CHEETAH, WALKER)}


def _task_domain(domain: str, task: str) -> Domain:
    d = get_domain(domain)
    if task not in d.tasks:
        raise DomainError(f"unknown task '{task}' for domain {domain}; valid tasks: " + ", ".join(d.tasks))
    return d


def available_tasks(domain: str) -> list[str]:
    """Task names of a domain, training tasks first."""
    return list(get_domain(domain).tasks)


def task_descriptions(domain: str) -> list[tuple[str, str]]:
    """(task, one line) for every task of a domain, for `drago list`."""
    return list(get_domain(domain).tasks.items())


def env_spec(domain: str) -> EnvSpec:
    """The sizes of a domain's observations and actions, and whether its actions are discrete."""
    return get_domain(domain).env_spec()


def make_env(domain: str, task: str, dense_reward: bool | None = None, render_mode: str | None = None,
             action_repeat: int | None = None, max_episode_steps: int | None = None) -> gym.Env:
    """Build the env of one task; seed it through ``reset(seed=...)``.

    Args:
        domain: minigrid, cheetah, walker or any registered domain or ``dmc:`` name (see
            :func:`available_domains`).
        task: a task of that domain (see :func:`available_tasks`).
        dense_reward: grid only (and domains that take it): override the task's reward type (None: the
            catalogue's).
        render_mode: ``"rgb_array"`` to allow ``env.render()``.
        action_repeat: simulator control steps per agent step, rewards summed (None: the domain's
            default: grid 1, cheetah 4, walker 2).
        max_episode_steps: agent steps after which ``truncated`` is reported (None: never; the trainer
            counts episode steps itself). The grid ignores it: its episodes are 100 steps.

    Raises:
        DomainError: an unknown domain or task, ``dense_reward`` for a domain without it, or an env
            whose spaces do not match the domain's sizes (one line).
    """
    d = _task_domain(domain, task)
    if dense_reward is not None and not d.dense_reward:
        takers = ["the grid" if name == "minigrid" else name for name in available_domains()
                  if get_domain(name).dense_reward]
        raise DomainError(f"dense_reward applies to {', '.join(takers) or 'no domain'} only, not to domain {domain}")
    repeat = d.action_repeat if action_repeat is None else action_repeat
    env = d.make(task, dense_reward, render_mode, repeat, max_episode_steps)
    _check_env(d, task, env)
    return env


def _check_env(d: Domain, task: str, env: gym.Env) -> None:
    spec = d.env_spec()
    obs, act = getattr(env, "observation_space", None), getattr(env, "action_space", None)
    shapes = (getattr(obs, "shape", None), getattr(act, "shape", None))
    if shapes != ((spec.obs_dim,), (spec.action_dim,)):
        env.close()
        raise DomainError(f"task '{task}' of domain {d.name} built an env with observation shape {shapes[0]} and "
                          f"action shape {shapes[1]}; the domain's spec says ({spec.obs_dim},) and "
                          f"({spec.action_dim},): a domain's tasks must share their sizes")


def exact_world(domain: str) -> str | None:
    """The exact world whose evaluations apply to a domain's runs (:attr:`Domain.exact_world`); None for a
    domain without one, or one that is not registered here (a plug-in that is not installed)."""
    return get_domain(domain).exact_world if is_domain(domain) else None


def task_optimum(domain: str, task: str, dense_reward: bool | None = None) -> float | None:
    """The exact optimal return of a task where one is known (grid: finite-horizon DP), else None."""
    d = get_domain(domain)
    if d.optimum is None:
        return None
    return _task_domain(domain, task).optimum(task, dense_reward)


# The official code's gymnasium id, so `gymnasium.make("MiniGrid-FourRooms-New", task="room2")` works.
gym.register(id="MiniGrid-FourRooms-New", entry_point="drago.envs.fourrooms:make_fourrooms",
             max_episode_steps=None)

__all__ = ["DMC_SEQUENCES", "DMC_TASKS", "DMC_TRANSFER_TASKS", "DOMAINS", "DOMAIN_SPECS", "ENTRY_POINT_GROUP",
           "GRID_DOMAIN",
           "GRID_SEQUENCES", "GRID_TASKS", "DmcTask", "DmcTransferTask", "Domain", "DomainError", "EnvSpec", "FlatEnv",
           "GridTask", "PluginProblem", "TransitionReward", "available_domains", "available_tasks", "domain_families",
           "env_spec", "exact_world", "get_domain", "get_grid_task", "gym_domain", "is_domain", "load_plugins", "make_env",
           "plugin_problems", "register_domain", "reward_variant", "source_of", "task_descriptions", "task_optimum",
           "unregister_domain"]
