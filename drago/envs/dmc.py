"""DeepMind Control behind a gymnasium API: the paper's cheetah and walker (paper Appendix C), and every
stock suite task as a ``dmc:`` domain (:class:`StockDMCEnv`, :func:`stock_domain`).

Every task of a domain runs on the stock dm_control XML and the stock initial-state distribution (the
official custom XMLs differ from stock only visually, docs: Environments, DeepMind Control); a task only chooses the reward,
computed by the pure functions below from the physics after each control step.

:class:`DMCEnv` (and :class:`StockDMCEnv`) differ from the official wrapper stack in two deliberate ways:

* the episode length is managed outside dm_control: the inner environment has an infinite time limit
  (the official code passes a step count as seconds, so it never times out either, paper Appendix C), and
  ``max_episode_steps`` only sets ``truncated``; stepping past it is allowed, for pre-rollouts;
* seeding: every reset draws the dm_control task's ``RandomState`` seed from ``env.np_random``, so the
  initial state depends only on that generator. Restoring its state (as a resumed run does) replays
  exactly the same initial states, and ``reset(seed=s)`` always gives the same first observation.

Rendering is headless through ``MUJOCO_GL``. When it is unset on a Linux machine without a display, the
first usable of ``egl`` and ``osmesa`` is chosen here before dm_control is imported (``off`` if neither
library is installed: stepping still works, rendering raises). Set ``MUJOCO_GL`` yourself to override.
"""

from __future__ import annotations

import ctypes.util
import logging
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from drago.envs.domain import ActionScaler, Domain, DomainError, EnvSpec
from drago.envs.tasks import DmcTask, get_dmc_task

__all__ = ["DMC_DOMAINS", "DMC_PREFIX", "DMCEnv", "DmcDomain", "StockDMCEnv", "cheetah_jump_and_run_reward",
           "cheetah_jump_reward", "cheetah_run_reward", "default_gl_backend", "reward_function", "stock_domain",
           "stock_problem", "stock_task_sizes", "walker_reward"]


@dataclass(frozen=True)
class DmcDomain:
    """Fixed facts of a domain (paper Appendix C table) and the official code's defaults."""

    obs_dim: int
    action_dim: int
    control_timestep: float  # seconds per control step (one dm_control step)
    action_repeat: int  # official default
    episode_length: int  # agent steps per episode (1000 control steps / action_repeat)


DMC_DOMAINS: dict[str, DmcDomain] = {
    # position = qpos[1:] (8) + velocity = qvel (9); physics dt = control dt = 0.01 s.
    "cheetah": DmcDomain(obs_dim=17, action_dim=6, control_timestep=0.01, action_repeat=4, episode_length=250),
    # orientations (xx, xz of 7 bodies: 14) + torso height (1) + velocity (9); 10 physics steps of 0.0025 s.
    "walker": DmcDomain(obs_dim=24, action_dim=6, control_timestep=0.025, action_repeat=2, episode_length=500),
}


# ------------------------------------------------------------------------------------------------
# Headless rendering backend
# ------------------------------------------------------------------------------------------------
def default_gl_backend() -> str | None:
    """The ``MUJOCO_GL`` value to use when the user set none: None where a display exists or off Linux."""
    if not sys.platform.startswith("linux") or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return None
    for backend, library in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(library):
            return backend
    return "off"


if "MUJOCO_GL" not in os.environ:
    _backend = default_gl_backend()
    if _backend is not None:
        os.environ["MUJOCO_GL"] = _backend


class _DropCompilerNotice(logging.Filter):
    """MuJoCo >= 3.3 warns on every compile of the stock cheetah XML that `settotalmass` is deprecated.
    The stock file is used on purpose (its masses are the benchmark's), so the notice is only noise."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "settotalmass" not in record.getMessage()


logging.getLogger("absl").addFilter(_DropCompilerNotice())

try:
    from dm_control import suite
    from dm_control.rl import control
    from dm_control.suite import cheetah, walker
    from dm_control.utils import rewards
except ImportError as err:  # pragma: no cover - exercised only without the extra
    raise ImportError("the DeepMind Control domains need dm_control: pip install 'drago[dmc]' "
                      f"(scripts/setup.sh installs it) [{err}]") from err


# ------------------------------------------------------------------------------------------------
# Rewards (paper Appendix C): pure functions of the physics after a control step
# ------------------------------------------------------------------------------------------------
CHEETAH_RUN_SPEED = 10.0
CHEETAH_JUMP_HEIGHT = 1.2
CHEETAH_JUMP_SPEED = 0.5  # |vx| allowed while jumping (the custom task's move_speed)
WALKER_STAND_HEIGHT = 1.2
_FEET = ("bfoot", "ffoot")
_INF = float("inf")


def _vx(physics) -> float:
    """x-velocity of the torso subtree's centre of mass (``speed()`` / ``horizontal_velocity()``)."""
    return float(physics.named.data.sensordata["torso_subtreelinvel"][0])


def _z(physics, body: str) -> float:
    return float(physics.named.data.xpos[body, "z"])


def cheetah_run_reward(physics, speed: float = CHEETAH_RUN_SPEED, direction: int = 1) -> float:
    """tol(vx; [S, inf), m=S, linear, v=0) forward; its mirror (-inf, -S] backward = clip(±vx/S, 0, 1)."""
    bounds = (speed, _INF) if direction >= 0 else (-_INF, -speed)
    return float(rewards.tolerance(_vx(physics), bounds=bounds, margin=speed, value_at_margin=0, sigmoid="linear"))


def _feet_height_terms(physics, height: float) -> list[float]:
    """tol((z_torso + z_f)/2; [h, inf), m=h/2, gaussian) for f in (bfoot, ffoot)."""
    torso = _z(physics, "torso")
    return [float(rewards.tolerance((torso + _z(physics, f)) / 2, bounds=(height, _INF), margin=height / 2))
            for f in _FEET]


def cheetah_jump_reward(physics) -> float:
    """Mean over both feet of TD-MPC2's stand-on-one-foot reward (5 h_f + s) / 6."""
    still = float(rewards.tolerance(_vx(physics), bounds=(-CHEETAH_JUMP_SPEED, CHEETAH_JUMP_SPEED),
                                    margin=CHEETAH_JUMP_SPEED, value_at_margin=0, sigmoid="linear"))
    return float(np.mean([(5 * h + still) / 6 for h in _feet_height_terms(physics, CHEETAH_JUMP_HEIGHT)]))


def cheetah_jump_and_run_reward(physics, speed: float = 7.5, direction: int = 1) -> float:
    """DRAGO's new tasks: (mean feet-height term at 0.9 m + clip(±vx/7.5, 0, 1)) / 2 (thresholds x 3/4)."""
    jump = float(np.mean(_feet_height_terms(physics, 0.75 * CHEETAH_JUMP_HEIGHT)))
    return (jump + cheetah_run_reward(physics, speed, direction)) / 2


def walker_reward(physics, speed: float, direction: int = 1) -> float:
    """stand if S = 0, else stand (5 move + 1) / 6 with move = tol(±vx; [S, inf), m=S/2, linear, v=0.5)."""
    standing = rewards.tolerance(_z(physics, "torso"), bounds=(WALKER_STAND_HEIGHT, _INF),
                                 margin=WALKER_STAND_HEIGHT / 2)
    upright = (1 + float(physics.named.data.xmat["torso", "zz"])) / 2
    stand = (3 * float(standing) + upright) / 4
    if speed == 0:
        return stand
    bounds = (speed, _INF) if direction >= 0 else (-_INF, -speed)
    move = float(rewards.tolerance(_vx(physics), bounds=bounds, margin=speed / 2, value_at_margin=0.5,
                                   sigmoid="linear"))
    return stand * (5 * move + 1) / 6


def reward_function(task: DmcTask | str) -> Callable[[Any], float]:
    """The reward of a catalogue task as a function of the physics."""
    task = get_dmc_task(task) if isinstance(task, str) else task
    if task.kind == "cheetah-run":
        return lambda physics: cheetah_run_reward(physics, task.speed, task.direction)
    if task.kind == "cheetah-jump":
        return cheetah_jump_reward
    if task.kind == "cheetah-jump-and-run":
        return lambda physics: cheetah_jump_and_run_reward(physics, task.speed, task.direction)
    if task.kind == "walker":
        return lambda physics: walker_reward(physics, task.speed, task.direction)
    raise ValueError(f"unknown reward kind {task.kind!r} of task {task.name}")


# ------------------------------------------------------------------------------------------------
# dm_control tasks: the stock ones with the reward replaced
# ------------------------------------------------------------------------------------------------
class _CheetahTask(cheetah.Cheetah):
    def __init__(self, reward: Callable[[Any], float], random=None):
        self._reward = reward
        super().__init__(random=random)

    def get_reward(self, physics):
        return self._reward(physics)


class _WalkerTask(walker.PlanarWalker):
    def __init__(self, reward: Callable[[Any], float], random=None):
        self._reward = reward
        super().__init__(move_speed=0, random=random)  # move_speed is read only by the stock reward

    def get_reward(self, physics):
        return self._reward(physics)


def _make_dm_env(task: DmcTask) -> control.Environment:
    reward = reward_function(task)
    if task.domain == "cheetah":
        physics = cheetah.Physics.from_xml_string(*cheetah.get_model_and_assets())
        return control.Environment(physics, _CheetahTask(reward), time_limit=_INF)
    physics = walker.Physics.from_xml_string(*walker.get_model_and_assets())
    return control.Environment(physics, _WalkerTask(reward), time_limit=_INF,
                               control_timestep=DMC_DOMAINS["walker"].control_timestep)


# ------------------------------------------------------------------------------------------------
# gymnasium wrappers
# ------------------------------------------------------------------------------------------------
class _DmControlEnv(gym.Env):
    """A dm_control ``control.Environment`` behind the gymnasium API: action repeat, a flat float32 state,
    the episode length outside dm_control and seeding from ``np_random`` (see the module docstring).

    drago's actions in [-1, 1] are clipped and mapped onto the actuators' range (the identity where that
    range is [-1, 1], as for cheetah and walker). When dm_control ends an episode (an infinite time limit
    leaves only a task's own termination, as in LQR), the episode goes on in an absorbing state: the
    last observation again, reward 0, ``terminated=True``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def _setup(self, env: control.Environment, action_repeat: int, max_episode_steps: int | None,
               render_mode: str | None, render_size: tuple[int, int], camera_id: int) -> None:
        self.action_repeat = int(action_repeat)
        if self.action_repeat < 1:
            raise ValueError(f"action_repeat must be >= 1, got {action_repeat}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"unsupported render_mode {render_mode!r}; use 'rgb_array' or None")
        self.max_episode_steps = max_episode_steps
        self.render_mode = render_mode
        self.render_size = render_size
        self.camera_id = camera_id
        self._env = env
        obs_dim = sum(int(np.prod(spec.shape)) for spec in env.observation_spec().values())
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        spec = env.action_spec()
        self._scale = ActionScaler(spec.minimum, spec.maximum, np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, spec.shape, dtype=np.float32)
        # One frame per agent step: cheetah 25 fps, walker 20 fps at the official action repeats.
        self.metadata = {**self.metadata, "render_fps": 1.0 / (env.control_timestep() * self.action_repeat)}
        self._steps = 0
        self._needs_reset = True
        self._terminated = False
        self._last_obs: np.ndarray | None = None

    @property
    def physics(self):
        """The dm_control physics (``physics.named.data.qpos`` and friends)."""
        return self._env.physics

    @property
    def elapsed_steps(self) -> int:
        """Agent steps since the last reset."""
        return self._steps

    @staticmethod
    def _flatten(observation: dict[str, Any]) -> np.ndarray:
        return np.concatenate([np.asarray(v, dtype=np.float32).ravel() for v in observation.values()])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        # The task's RandomState is re-seeded from np_random at every reset: the initial state is a
        # function of np_random's state alone, which is what a checkpoint saves and restores.
        self._env.task._random = np.random.RandomState(int(self.np_random.integers(2**32)))
        time_step = self._env.reset()
        self._steps = 0
        self._needs_reset = False
        self._terminated = False
        self._last_obs = self._flatten(time_step.observation)
        return self._last_obs.copy(), {}

    def step(self, action):
        if self._needs_reset:
            raise RuntimeError("call reset() before step()")
        action = self._scale(action)
        reward = 0.0
        if not self._terminated:
            for _ in range(self.action_repeat):
                time_step = self._env.step(action)
                reward += time_step.reward or 0.0
                if time_step.last():  # with the infinite time limit, only a task's own termination
                    self._terminated = True
                    break
            self._last_obs = self._flatten(time_step.observation)
        self._steps += 1
        truncated = self.max_episode_steps is not None and self._steps >= self.max_episode_steps
        return self._last_obs.copy(), float(reward), self._terminated, bool(truncated), {}

    def render(self):
        if self.render_mode != "rgb_array":
            raise RuntimeError("create the env with render_mode='rgb_array' to render")
        height, width = self.render_size
        return self.physics.render(height=height, width=width, camera_id=self.camera_id)

    def close(self):
        # Free the GL context now rather than at interpreter exit, where osmesa prints tracebacks. The
        # physics stays usable; a later render() makes a new context.
        physics = self.physics
        with physics._contexts_lock:
            if physics._contexts:
                physics._free_rendering_contexts()


class DMCEnv(_DmControlEnv):
    """One DeepMind Control task with action repeat, a flat float32 state and external episode length.

    Args:
        task: a key of :data:`drago.envs.tasks.DMC_TASKS` (e.g. ``"cheetah-run"``) or the task itself.
        action_repeat: control steps per agent step; rewards are summed over them (None: the domain's
            official value, 4 cheetah / 2 walker).
        max_episode_steps: agent steps after which ``step`` reports ``truncated=True`` (None: never).
            The environment keeps stepping past it; only the caller ends an episode.
        render_mode: ``"rgb_array"`` to allow :meth:`render`.
        render_size: (height, width) of rendered frames.
        camera_id: dm_control camera (0: the tracking camera of both domains).

    Observations are the dm_control observation dict flattened in its order (cheetah: position,
    velocity; walker: orientations, height, velocity). Actions are clipped to [-1, 1], the actuators'
    range. ``terminated`` is always False: these tasks never end early.
    """

    def __init__(self, task: DmcTask | str, action_repeat: int | None = None, max_episode_steps: int | None = None,
                 render_mode: str | None = None, render_size: tuple[int, int] = (240, 320), camera_id: int = 0):
        self.task = get_dmc_task(task) if isinstance(task, str) else task
        domain = DMC_DOMAINS[self.task.domain]
        self._setup(_make_dm_env(self.task), domain.action_repeat if action_repeat is None else action_repeat,
                    max_episode_steps, render_mode, render_size, camera_id)


# ------------------------------------------------------------------------------------------------
# Every stock dm_control task: the dmc:DOMAIN domains
# ------------------------------------------------------------------------------------------------
DMC_PREFIX = "dmc:"
#: Agent steps per episode and the action repeat of every ``dmc:`` domain: the suite's 1000 control
#: steps at TD-MPC's usual action repeat of 2.
STOCK_ACTION_REPEAT = 2
STOCK_EPISODE_LENGTH = 500


class StockDMCEnv(_DmControlEnv):
    """A stock dm_control suite task (``suite.load(domain, task)``), its own reward, no time limit.

    Args:
        domain: A dm_control suite domain, e.g. ``"hopper"``.
        task: One of its tasks, e.g. ``"stand"``.
        action_repeat: Control steps per agent step, rewards summed.
        max_episode_steps: Agent steps after which ``truncated`` is reported (None: never).
        render_mode: ``"rgb_array"`` to allow :meth:`render`.
        render_size: (height, width) of rendered frames.
        camera_id: dm_control camera.
    """

    def __init__(self, domain: str, task: str, action_repeat: int = STOCK_ACTION_REPEAT,
                 max_episode_steps: int | None = None, render_mode: str | None = None,
                 render_size: tuple[int, int] = (240, 320), camera_id: int = 0):
        self.suite_task = (domain, task)
        env = suite.load(domain, task, task_kwargs={"time_limit": _INF})
        self._setup(env, action_repeat, max_episode_steps, render_mode, render_size, camera_id)


def _suite_tasks() -> dict[str, list[str]]:
    tasks: dict[str, list[str]] = {}
    for domain, task in suite.ALL_TASKS:
        tasks.setdefault(domain, []).append(task)
    return tasks


_SIZES: dict[tuple[str, str], tuple[int, int]] = {}


def stock_task_sizes(domain: str, task: str) -> tuple[int, int]:
    """(obs_dim, action_dim) of a stock task, read from its specs (one env built, once per process)."""
    key = (domain, task)
    if key not in _SIZES:
        env = suite.load(domain, task, task_kwargs={"time_limit": _INF})
        _SIZES[key] = (sum(int(np.prod(s.shape)) for s in env.observation_spec().values()),
                       int(np.prod(env.action_spec().shape)))
    return _SIZES[key]


def stock_problem(name: str) -> str | None:
    """Why ``name`` is not a ``dmc:DOMAIN`` or ``dmc:DOMAIN-TASK`` domain (one line), or None. Builds nothing."""
    suite_tasks = _suite_tasks()
    domain, _, task = name[len(DMC_PREFIX):].partition("-")
    if domain not in suite_tasks:
        return (f"unknown domain '{name}': dmc: takes a dm_control suite domain, e.g. dmc:hopper or "
                f"dmc:quadruped-walk; domains: {', '.join(sorted(suite_tasks))}")
    if task and task not in suite_tasks[domain]:
        return (f"unknown domain '{name}': dm_control's {domain} has no task '{task}'; tasks: "
                f"{', '.join(suite_tasks[domain])}")
    return None


def stock_domain(name: str) -> Domain:
    """The ``dmc:`` domain ``name``: ``dmc:DOMAIN`` or ``dmc:DOMAIN-TASK``.

    Its tasks, named ``DOMAIN-TASK`` (``hopper-stand``), are the stock tasks of the dm_control domain
    that share the observation and action sizes of its first task (``dmc:DOMAIN``) or of ``TASK``
    (``dmc:DOMAIN-TASK``, which comes first): for most domains every task, while finger-spin and
    finger-turn_easy, say, differ in size and so fall into ``dmc:finger`` and ``dmc:finger-turn_easy``.
    Building it reads each task's sizes from one env (cached).

    Raises:
        DomainError: Not a dm_control domain or task (one line listing valid ones).
    """
    problem = stock_problem(name)
    if problem:
        raise DomainError(problem)
    domain, _, first = name[len(DMC_PREFIX):].partition("-")
    stock = _suite_tasks()[domain]
    first = first or stock[0]
    sizes = stock_task_sizes(domain, first)
    members = [first] + [t for t in stock if t != first and stock_task_sizes(domain, t) == sizes]
    benchmark = {task for d, task in suite.BENCHMARKING if d == domain}
    tasks = {f"{domain}-{t}": f"stock dm_control {domain} {t}, its own reward"
             + ("" if t in benchmark else " (extra task)") for t in members}
    others = [t for t in stock if t not in members]

    def make(task: str, dense_reward: bool | None = None, render_mode: str | None = None,
             action_repeat: int | None = None, max_episode_steps: int | None = None) -> StockDMCEnv:
        return StockDMCEnv(domain, task.split("-", 1)[1], action_repeat or STOCK_ACTION_REPEAT,
                           max_episode_steps, render_mode)

    note = f"; tasks of other sizes: {', '.join(f'dmc:{domain}-{t}' for t in others)}" if others else ""
    return Domain(name=name, spec=EnvSpec(name, sizes[0], sizes[1], False), tasks=tasks, make=make,
                  episode_length=STOCK_EPISODE_LENGTH, action_repeat=STOCK_ACTION_REPEAT, requires=("dm_control",),
                  description=f"dm_control suite {domain}, stock tasks{note}")
