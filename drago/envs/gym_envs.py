"""Any gymnasium environment as a drago domain: :func:`gym_domain`, :class:`FlatEnv`, reward variants.

A gymnasium env with a Box observation space and a Box or Discrete action space becomes what drago's
agent expects (:class:`FlatEnv`):

* observations flattened to float32 vectors;
* a Box action space takes drago's actions in [-1, 1], rescaled to the env's bounds;
* a Discrete(n) action space takes a one-hot float vector of length n (its argmax), as the grid does;
* action repeat sums the rewards; the episode length is the trainer's: the env's own time limit is
  ignored, and when the env terminates (CartPole's pole falls) the episode goes on in an absorbing
  state: the last observation again, reward 0, ``terminated=True``;
* seeding: every reset draws the inner env's seed from ``env.np_random``, so ``reset(seed=s)`` gives
  the same first observation and restoring ``np_random`` (a resumed run) replays the same episodes.

Tasks of one domain share the dynamics and differ in the reward: the same env id with different
keyword arguments, or one env id behind reward wrappers (:func:`reward_variant`).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from drago.envs.domain import ActionScaler, Domain, DomainError, EnvSpec, one_line

__all__ = ["FlatEnv", "TaskSource", "TransitionReward", "gym_domain", "gym_family_domain", "gym_family_problem",
           "reward_variant"]

#: What a task of :func:`gym_domain` is built from: a gymnasium id, ``(id, kwargs)`` or a callable returning
#: an env (called with ``render_mode=`` when it takes that argument).
TaskSource = str | tuple[str, Mapping[str, Any]] | Callable[..., gym.Env]


def _label(source: TaskSource) -> str:
    if isinstance(source, str):
        return source
    if isinstance(source, tuple):
        env_id, kwargs = source
        args = ", ".join(f"{k}={v!r}" for k, v in dict(kwargs).items())
        return f"{env_id}({args})" if args else env_id
    return getattr(source, "label", None) or getattr(source, "__qualname__", None) or repr(source)


def _accepts_render_mode(fn: Callable[..., Any]) -> bool:
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == "render_mode" or p.kind is inspect.Parameter.VAR_KEYWORD for p in params)


def _build_source(source: TaskSource, render_mode: str | None = None, where: str = "") -> gym.Env:
    """The gymnasium env of a task source; gymnasium's errors become one-line :class:`DomainError`."""
    label = _label(source)
    try:
        if isinstance(source, str):
            env = gym.make(source, render_mode=render_mode)
        elif isinstance(source, tuple) and len(source) == 2 and isinstance(source[0], str):
            env = gym.make(source[0], render_mode=render_mode, **dict(source[1]))
        elif callable(source):
            env = source(render_mode=render_mode) if _accepts_render_mode(source) else source()
        else:
            raise DomainError(f"{where}a task is an env id, (env id, kwargs) or a callable returning an env, "
                              f"got {type(source).__name__}")
    except DomainError:
        raise
    except Exception as err:  # noqa: BLE001 - gymnasium's NameNotFound, DependencyNotInstalled, a bad kwarg, ...
        raise DomainError(f"{where}cannot make env '{label}': {type(err).__name__}: {one_line(err)}") from None
    if not isinstance(env, gym.Env):
        raise DomainError(f"{where}'{label}' returned {type(env).__name__}, not a gymnasium.Env")
    return env


def _spaces_problem(env: gym.Env, label: str) -> str | None:
    obs, act = env.observation_space, env.action_space
    ok_obs = isinstance(obs, gym.spaces.Box)
    ok_act = isinstance(act, (gym.spaces.Discrete, gym.spaces.Box))
    if ok_obs and ok_act:
        return None
    return (f"env '{label}' has observation space {one_line(obs, 120)} and action space {one_line(act, 120)}; "
            "drago needs a Box observation space and a Box or Discrete action space (wrap the env to flatten it)")


class FlatEnv(gym.Env):
    """A gymnasium env as drago's agent sees it (see the module docstring).

    Args:
        env: The inner env: a Box observation space, a Box or Discrete action space.
        label: Its name in error messages (the env id).
        action_repeat: Inner steps per agent step, rewards summed.
        max_episode_steps: Agent steps after which ``truncated`` is reported (None: never).

    Raises:
        DomainError: Another observation or action space (one line naming the env and its spaces).
    """

    def __init__(self, env: gym.Env, label: str = "", action_repeat: int = 1,
                 max_episode_steps: int | None = None) -> None:
        label = label or type(env.unwrapped).__name__
        problem = _spaces_problem(env, label)
        if problem:
            raise DomainError(problem)
        if int(action_repeat) < 1:
            raise ValueError(f"action_repeat must be >= 1, got {action_repeat}")
        self.env = env
        self.label = label
        self.action_repeat = int(action_repeat)
        self.max_episode_steps = max_episode_steps
        self.render_mode = getattr(env, "render_mode", None)
        obs = env.observation_space
        self.observation_space = gym.spaces.Box(np.asarray(obs.low, np.float32).ravel(),
                                                np.asarray(obs.high, np.float32).ravel(), dtype=np.float32)
        act = env.action_space
        if isinstance(act, gym.spaces.Discrete):
            self.discrete = True
            self._n, self._start = int(act.n), int(act.start)
            self.action_space = gym.spaces.Box(0.0, 1.0, (self._n,), np.float32)
        else:
            self.discrete = False
            self._scale = ActionScaler(act.low, act.high, act.dtype if act.dtype is not None else np.float32)
            self.action_space = gym.spaces.Box(-1.0, 1.0, (self._scale.size,), np.float32)
        fps = env.metadata.get("render_fps")
        self.metadata = {"render_modes": list(env.metadata.get("render_modes", [])),
                         "render_fps": fps / self.action_repeat if fps else fps}
        self._steps = 0
        self._last_obs: np.ndarray | None = None
        self._terminated = False

    @property
    def elapsed_steps(self) -> int:
        """Agent steps since the last reset."""
        return self._steps

    def _flat(self, obs: Any) -> np.ndarray:
        return np.asarray(obs, dtype=np.float32).reshape(-1)

    def native_action(self, action: Any) -> Any:
        """drago's action as the inner env takes it (an int for Discrete, bounds for Box)."""
        if self.discrete:
            if isinstance(action, (int, np.integer)):
                return int(action)
            vec = np.asarray(action).reshape(-1)
            if vec.shape != (self._n,):
                raise ValueError(f"action must be an int or a one-hot vector of length {self._n}, got shape "
                                 f"{np.shape(action)}")
            return self._start + int(vec.argmax())
        return self._scale(action)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=int(self.np_random.integers(2**31 - 1)), options=options)
        self._steps = 0
        self._terminated = False
        self._last_obs = self._flat(obs)
        return self._last_obs.copy(), info

    def step(self, action):
        if self._last_obs is None:
            raise RuntimeError("call reset() before step()")
        native = self.native_action(action)
        reward, info = 0.0, {}
        if not self._terminated:
            for _ in range(self.action_repeat):
                obs, r, terminated, _, info = self.env.step(native)  # the inner time limit is ignored
                reward += float(r)
                if terminated:  # absorbing from here on: same observation, reward 0
                    self._terminated = True
                    break
            self._last_obs = self._flat(obs)
        self._steps += 1
        truncated = self.max_episode_steps is not None and self._steps >= self.max_episode_steps
        return self._last_obs.copy(), float(reward), self._terminated, bool(truncated), info

    def render(self):
        return self.env.render()

    def close(self):
        self.env.close()


class TransitionReward(gym.Wrapper):
    """Replaces an env's reward by ``reward(obs, action, next_obs)`` (the env's own action and
    observations), keeping its dynamics: one task of a reward family."""

    def __init__(self, env: gym.Env, reward: Callable[[Any, Any, Any], float]) -> None:
        super().__init__(env)
        self.reward_fn = reward
        self._obs: Any = None

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._obs = obs
        return obs, info

    def step(self, action):
        obs, stock, terminated, truncated, info = self.env.step(action)
        reward = float(self.reward_fn(self._obs, action, obs))
        self._obs = obs
        return obs, reward, terminated, truncated, {**info, "stock_reward": stock}


def reward_variant(env_id: str, reward: Callable[[Any, Any, Any], float], label: str | None = None,
                   **kwargs: Any) -> Callable[..., gym.Env]:
    """A task source for :func:`gym_domain`: ``gym.make(env_id, **kwargs)`` with its reward replaced.

    Args:
        env_id: The gymnasium id whose dynamics the task keeps.
        reward: ``reward(obs, action, next_obs) -> float`` in the env's own terms.
        label: Its name in descriptions (default: ``env_id`` and the function's name).
        **kwargs: Keyword arguments for ``gym.make``.

    Returns:
        A callable ``make(render_mode=None) -> gymnasium.Env``.
    """

    def make(render_mode: str | None = None) -> gym.Env:
        return TransitionReward(gym.make(env_id, render_mode=render_mode, **kwargs), reward)

    make.label = label or f"{env_id} with reward {getattr(reward, '__name__', 'custom')}"  # type: ignore[attr-defined]
    make.env_id = env_id  # type: ignore[attr-defined]
    return make


def gym_domain(name: str, tasks: Mapping[str, TaskSource], episode_length: int, action_repeat: int = 1,
               optimum: Mapping[str, float] | Callable[[str, bool | None], float | None] | None = None,
               descriptions: Mapping[str, str] | None = None,
               sequences: Mapping[str, tuple[str, ...]] | None = None, description: str = "",
               requires: tuple[str, ...] = ()) -> Domain:
    """A :class:`~drago.envs.domain.Domain` from gymnasium environments, one per task.

    Nothing is built here: the sizes are read from the first task's env on first use (``env_spec``),
    and every env that ``make_env`` builds is checked against them.

    Args:
        name: The domain's name.
        tasks: Task name to its source: a gymnasium id, ``(id, kwargs)``, or a callable returning an env
            (for instance :func:`reward_variant`); training tasks first. All tasks should share dynamics.
        episode_length: Default agent steps per episode.
        action_repeat: Default inner steps per agent step.
        optimum: Known optimal returns: a dict task -> return, or ``optimum(task, dense_reward)``.
        descriptions: Task name to a one-line description (default: the source's id or label).
        sequences: Named continual sequences of task names.
        description: One line on the domain.
        requires: Modules the domain needs, for a config check.

    Returns:
        The domain, not yet registered: pass it to ``register_domain``.
    """
    sources = dict(tasks)
    if not sources:
        raise DomainError(f"domain '{name}': tasks must name at least one env")
    descriptions = dict(descriptions or {})
    unknown = [t for t in descriptions if t not in sources]
    if unknown:
        raise DomainError(f"domain '{name}': descriptions name unknown tasks {unknown}; tasks: {', '.join(sources)}")
    lines = {task: descriptions.get(task) or f"gymnasium {_label(source)}" for task, source in sources.items()}
    default_repeat = action_repeat

    def build(task: str, render_mode: str | None, action_repeat: int, max_episode_steps: int | None) -> FlatEnv:
        source = sources[task]
        where = f"domain '{name}', task '{task}': "
        env = _build_source(source, render_mode, where)
        problem = _spaces_problem(env, _label(source))
        if problem:
            env.close()
            raise DomainError(where + problem)
        return FlatEnv(env, _label(source), action_repeat, max_episode_steps)

    def make(task: str, dense_reward: bool | None = None, render_mode: str | None = None,
             action_repeat: int | None = None, max_episode_steps: int | None = None) -> FlatEnv:
        return build(task, render_mode, action_repeat or default_repeat, max_episode_steps)

    def spec() -> EnvSpec:
        env = build(next(iter(sources)), None, 1, None)
        try:
            return EnvSpec(name, int(env.observation_space.shape[0]), int(env.action_space.shape[0]), env.discrete)
        finally:
            env.close()

    if isinstance(optimum, Mapping):
        known = {str(k): float(v) for k, v in optimum.items()}
        bad = [t for t in known if t not in sources]
        if bad:
            raise DomainError(f"domain '{name}': optimum names unknown tasks {bad}; tasks: {', '.join(sources)}")
        optimum_fn: Callable[[str, bool | None], float | None] | None = lambda task, dense=None: known.get(task)
    else:
        optimum_fn = optimum
    return Domain(name=name, spec=spec, tasks=lines, make=make, episode_length=episode_length,
                  action_repeat=action_repeat, optimum=optimum_fn, sequences=dict(sequences or {}),
                  description=description, requires=tuple(requires))


# ------------------------------------------------------------------------------------------------
# The gym: family: every registered gymnasium id as a one-task domain, gym:ID
# ------------------------------------------------------------------------------------------------
GYM_PREFIX = "gym:"


def gym_family_problem(name: str) -> str | None:
    """Why ``name`` is not a ``gym:ID`` domain (one line), or None if gymnasium knows ``ID``."""
    env_id = name[len(GYM_PREFIX):]
    try:
        gym.spec(env_id)
    except Exception as err:  # noqa: BLE001 - any failure to find the id is the answer
        return (f"unknown domain '{name}': gym: takes a registered gymnasium id, e.g. gym:Pendulum-v1 "
                f"({type(err).__name__}: {one_line(err, 160)})")
    return None


def gym_family_domain(name: str) -> Domain:
    """``gym:ID``: the gymnasium env ``ID`` with its own reward, one task named ``ID``, its own time
    limit as the default episode length (1000 where it has none)."""
    problem = gym_family_problem(name)
    if problem:
        raise DomainError(problem)
    env_id = name[len(GYM_PREFIX):]
    length = gym.spec(env_id).max_episode_steps or 1000
    return gym_domain(name, {env_id: env_id}, episode_length=int(length),
                      descriptions={env_id: f"gymnasium {env_id}, its own reward"},
                      description=f"the gymnasium env {env_id}")
