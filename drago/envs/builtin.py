"""The built-in domains as :class:`~drago.envs.domain.Domain` data: the paper's four-rooms grid, cheetah
and walker, and a small example of a reward family on fixed dynamics, gymnasium's pendulum.

Nothing heavy is imported here: the grid and dm_control are imported by the factories, on first use.
"""

from __future__ import annotations

from drago.envs.domain import Domain, EnvSpec
from drago.envs.gym_envs import gym_domain, reward_variant
from drago.envs.tasks import DMC_SEQUENCES, DMC_TASKS, DMC_TRANSFER_TASKS, GRID_SEQUENCES, GRID_TASKS, get_grid_task

__all__ = ["BUILTIN_DOMAINS", "CHEETAH", "GRID_DOMAIN", "MINIGRID", "PENDULUM", "PENDULUM_TASKS", "WALKER", "pendulum_keep_low_reward",
           "pendulum_spin_reward"]


# ---- the four-rooms grid ---------------------------------------------------------------------------
def _make_grid(task: str, dense_reward: bool | None = None, render_mode: str | None = None,
               action_repeat: int | None = None, max_episode_steps: int | None = None):
    from drago.envs.fourrooms import FourRoomsEnv

    if action_repeat not in (None, 1):
        raise ValueError(f"the grid has no action repeat; got action_repeat={action_repeat}")
    return FourRoomsEnv(get_grid_task(task, dense=dense_reward), render_mode=render_mode)


def _grid_optimum(task: str, dense_reward: bool | None = None) -> float:
    from drago.envs.fourrooms import optimal_return

    return optimal_return(get_grid_task(task, dense=dense_reward))


def _grid_reward(task: str, dense_reward: bool | None = None):
    from drago.envs.grid_reward import true_reward  # imports torch: only when a planner asks for it

    grid_task = get_grid_task(task, dense=dense_reward)
    return lambda obs, action, next_obs: true_reward(grid_task, obs, action, next_obs)


MINIGRID = Domain(
    name="minigrid",
    spec=EnvSpec("minigrid", obs_dim=3, action_dim=3, discrete=True),
    # The catalogue's description already names start and goal.
    tasks={name: f"{t.description}; {'dense' if t.dense else 'sparse'} reward" for name, t in GRID_TASKS.items()},
    make=_make_grid, episode_length=100, action_repeat=1, optimum=_grid_optimum, tabular=True,
    sequences=GRID_SEQUENCES, dense_reward=True, requires=("minigrid",),
    description="the paper's 27 x 27 four-rooms grid (drago/envs/fourrooms.py)",
    # Paper Appendix C: the test tasks and the stage of the sequence each is learned after.
    transfer_cases=(("room1to2", 2), ("room1to3", 3), ("room1to3", 4), ("room3to4", 4)),
    dense_by_default={name: t.dense for name, t in GRID_TASKS.items()},
    known_reward=_grid_reward, exact_world="four-rooms",
)

#: The domain that builds the four-rooms world's envs, for the exact evaluations that step it.
GRID_DOMAIN = MINIGRID.name


# ---- DeepMind Control: cheetah and walker ------------------------------------------------------------
def _make_dmc(task: str, dense_reward: bool | None = None, render_mode: str | None = None,
              action_repeat: int | None = None, max_episode_steps: int | None = None):
    from drago.envs.dmc import (
        DMCEnv,  # imports dm_control: only when a DMC env is built
    )

    return DMCEnv(task, action_repeat=action_repeat, max_episode_steps=max_episode_steps, render_mode=render_mode)


def _dmc_domain(name: str, obs_dim: int, action_repeat: int, episode_length: int, what: str) -> Domain:
    # The sizes are checked against dm_control in tests/test_dmc.py; here they need no import of it.
    return Domain(
        name=name, spec=EnvSpec(name, obs_dim=obs_dim, action_dim=6, discrete=False),
        tasks={t: f"{task.description}; reward {task.reward}" for t, task in DMC_TASKS.items() if task.domain == name},
        make=_make_dmc, episode_length=episode_length, action_repeat=action_repeat,
        sequences={name: DMC_SEQUENCES[name]}, requires=("dm_control",), description=what,
        # Paper §4.4, Table 1: the test tasks and the stage of the paper's sequence each is learned after.
        transfer_cases=tuple((t.name, t.stage) for t in DMC_TRANSFER_TASKS.values() if t.domain == name),
    )


CHEETAH = _dmc_domain("cheetah", 17, 4, 250, "DeepMind Control cheetah, the paper's rewards (drago/envs/dmc.py)")
WALKER = _dmc_domain("walker", 24, 2, 500, "DeepMind Control walker, the paper's rewards (drago/envs/dmc.py)")


# ---- an example reward family on fixed dynamics: gymnasium's Pendulum-v1 -----------------------------
# Observations are (cos th, sin th, th_dot) with th = 0 upright; th_dot is clipped to [-8, 8].
def pendulum_spin_reward(obs, action, next_obs) -> float:
    """Spin: |th_dot| / 8 in [0, 1], the pendulum's speed as a fraction of its maximum."""
    return float(min(abs(next_obs[2]) / 8.0, 1.0))


def pendulum_keep_low_reward(obs, action, next_obs) -> float:
    """Keep low: (1 - cos th) / 2 in [0, 1], 1 hanging straight down, 0 upright."""
    return float((1.0 - next_obs[0]) / 2.0)


PENDULUM_TASKS = {
    "pendulum-swingup": "Pendulum-v1",
    "pendulum-keep-low": reward_variant("Pendulum-v1", pendulum_keep_low_reward, label="Pendulum-v1, keep-low reward"),
    "pendulum-spin": reward_variant("Pendulum-v1", pendulum_spin_reward, label="Pendulum-v1, spin reward"),
}

PENDULUM = gym_domain(
    "pendulum", PENDULUM_TASKS, episode_length=200,
    descriptions={
        "pendulum-swingup": "gymnasium Pendulum-v1 as is: swing up and balance; "
                            "reward -(th^2 + 0.1 th_dot^2 + 0.001 u^2)",
        "pendulum-keep-low": "stay low, damping the swing; reward (1 - cos th)/2",
        "pendulum-spin": "spin as fast as possible; reward |th_dot|/8",
    },
    sequences={"pendulum": ("pendulum-keep-low", "pendulum-spin", "pendulum-swingup")},
    description="gymnasium Pendulum-v1 with three rewards on the same dynamics (an example of a reward family)",
)

#: Registered by :mod:`drago.envs.registry` on import, in this order.
BUILTIN_DOMAINS: tuple[Domain, ...] = (MINIGRID, CHEETAH, WALKER, PENDULUM)
