"""What a domain is: an :class:`EnvSpec`, its tasks as data and a factory of gymnasium environments.

This module holds only the types (:class:`EnvSpec`, :class:`Domain`, :class:`DomainError`) and the
action conversion shared by the wrappers; the registry of named domains lives in
:mod:`drago.envs.registry`. It imports nothing else of drago.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from drago.plugins import one_line  # re-exported: the domain modules say what to fix in one line

__all__ = ["EXACT_WORLDS", "ActionScaler", "Domain", "DomainError", "EnvSpec", "RewardFunction", "one_line"]

#: The worlds whose every transition drago's exact evaluations can enumerate and step (coverage, zero-shot
#: planning, per-component probes, heatmaps, visitation maps): today one, the paper's four-rooms map.
EXACT_WORLDS = ("four-rooms",)


class DomainError(ValueError):
    """A bad domain, domain name, task or environment; the message is one line that says what to fix."""


@dataclass(frozen=True)
class EnvSpec:
    """What the agent needs to know about a domain."""

    domain: str
    obs_dim: int
    action_dim: int
    discrete: bool  # one-hot actions and a categorical planner


#: Signature of :attr:`Domain.make`.
EnvFactory = Callable[..., Any]
#: ``reward(obs, action, next_obs)`` on batched tensors, returning one reward per row: a task's true reward.
RewardFunction = Callable[[Any, Any, Any], Any]

_TASK_NAME = re.compile(r"[^\s,\[\]=\"']+")


@dataclass(frozen=True, eq=False, kw_only=True)
class Domain:
    """A domain: data plus a factory. Tasks share the dynamics and differ in their reward.

    Register one with :func:`~drago.envs.registry.register_domain`; :func:`~drago.envs.gym_envs.gym_domain`
    builds one from gymnasium environments.

    Attributes:
        name: The domain's name, as in ``env.domain=NAME``.
        spec: The sizes (an :class:`EnvSpec` whose ``domain`` is ``name``), or a zero-argument callable
            returning them, called on first use and cached (to read them from a built env lazily).
        tasks: Task name to a one-line description, training tasks first.
        make: ``make(task, dense_reward, render_mode, action_repeat, max_episode_steps)`` (called with
            these five, in this order) returns a ``gymnasium.Env`` whose observations are flat float32
            vectors of ``obs_dim`` and whose actions are what drago's agent emits: a float vector in
            [-1, 1] of ``action_dim``, or, if discrete, a one-hot float vector of length ``action_dim``.
            ``action_repeat`` arrives as an int (the domain's default filled in), ``dense_reward`` as
            None unless the domain accepts it, ``max_episode_steps`` as None (never truncate) or the
            agent steps after which ``truncated`` is reported.
        episode_length: Default agent steps per episode (the trainer's ``env.episode_length``).
        action_repeat: Default simulator steps per agent step, rewards summed.
        optimum: ``optimum(task, dense_reward)``: the exact optimal return of a task, or None where
            unknown; None: unknown for every task.
        tabular: True for a small discrete world whose every transition can be enumerated (the grid's
            coverage and dynamic-programming optimum need it).
        sequences: Named continual task sequences, each a tuple of task names.
        dense_reward: True if the domain takes ``dense_reward`` (a dense or a sparse reward per task).
        requires: Modules the domain needs (``("dm_control",)``), for a config check before a run.
        description: One line on the domain, for ``drago list``.
        transfer_cases: The domain's standard few-shot transfer cases, ``(test task, after stage K)`` of its
            first sequence: what ``drago study`` and ``drago transfer --paper-cases`` run (the paper's, for the
            built-in domains). A test task is a task of the domain or a name ``drago transfer`` resolves
            (DeepMind Control's test tasks of the paper's Table 1).
        dense_by_default: For a domain that takes ``dense_reward``: each task's reward when none is asked
            (True: dense); a task left out has no default the reports can name.
        known_reward: ``known_reward(task, dense_reward)`` returns the task's true reward as a
            :data:`RewardFunction` of observations, for planners told the reward (PETS's
            ``agent.pets.reward=known``) and zero-shot planning; None: the reward is known only to the env.
        exact_world: One of :data:`EXACT_WORLDS` when the domain's dynamics are that world's, whatever its
            tasks: coverage, heatmaps and visitation maps then apply to its runs (zero-shot planning and the
            component probes too, for tasks of the grid's catalogue, whose rewards and optima they read).
            None: the domain's runs get the sampled held-out sets instead.
    """

    name: str
    spec: EnvSpec | Callable[[], EnvSpec]
    tasks: Mapping[str, str]
    make: EnvFactory
    episode_length: int
    action_repeat: int = 1
    optimum: Callable[[str, bool | None], float | None] | None = None
    tabular: bool = False
    sequences: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    dense_reward: bool = False
    requires: tuple[str, ...] = ()
    description: str = ""
    transfer_cases: tuple[tuple[str, int], ...] = ()
    dense_by_default: Mapping[str, bool] = field(default_factory=dict)
    known_reward: Callable[[str, bool | None], RewardFunction] | None = None
    exact_world: str | None = None
    _cache: dict[str, Any] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        name = self.name
        if not isinstance(name, str) or not name or any(c.isspace() for c in name):
            raise DomainError(f"a domain needs a non-empty name without spaces, got {name!r}")
        where = f"domain '{name}'"
        if not isinstance(self.tasks, Mapping) or not self.tasks:
            raise DomainError(f"{where}: tasks must be a non-empty dict of task name -> one-line description")
        for task, text in self.tasks.items():
            if not isinstance(task, str) or not _TASK_NAME.fullmatch(task):
                raise DomainError(f"{where}: bad task name {task!r}; use a string without spaces, commas, "
                                  "brackets, '=' or quotes")
            if not isinstance(text, str):
                raise DomainError(f"{where}: the description of task '{task}' must be a string")
        object.__setattr__(self, "tasks", MappingProxyType(dict(self.tasks)))
        if not callable(self.make):
            raise DomainError(f"{where}: make must be a callable make(task, dense_reward, render_mode, "
                              "action_repeat, max_episode_steps) returning a gymnasium.Env")
        if isinstance(self.spec, EnvSpec):
            self._check_spec(self.spec)
        elif not callable(self.spec):
            raise DomainError(f"{where}: spec must be an EnvSpec or a zero-argument callable returning one, "
                              f"got {type(self.spec).__name__}")
        for key in ("episode_length", "action_repeat"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise DomainError(f"{where}: {key} must be an int >= 1, got {value!r}")
        if self.optimum is not None and not callable(self.optimum):
            raise DomainError(f"{where}: optimum must be None or a callable optimum(task, dense_reward)")
        sequences = {}
        for seq, members in dict(self.sequences).items():
            members = (members,) if isinstance(members, str) else tuple(members)
            unknown = [t for t in members if t not in self.tasks]
            if not members or unknown:
                raise DomainError(f"{where}: sequence '{seq}' names unknown tasks {unknown or '(none)'}; "
                                  f"valid tasks: {', '.join(self.tasks)}")
            sequences[seq] = members
        object.__setattr__(self, "sequences", MappingProxyType(sequences))
        object.__setattr__(self, "requires", tuple(self.requires))
        self._check_capabilities(where)

    def _check_capabilities(self, where: str) -> None:
        cases = []
        for case in self.transfer_cases:
            task, after = case if isinstance(case, (tuple, list)) and len(case) == 2 else (None, None)
            if (not isinstance(task, str) or not _TASK_NAME.fullmatch(task) or isinstance(after, bool)
                    or not isinstance(after, int) or after < 1):
                raise DomainError(f"{where}: transfer case {case!r} must be (task name, stage K >= 1)")
            cases.append((task, after))
        object.__setattr__(self, "transfer_cases", tuple(cases))
        unknown = [t for t in self.dense_by_default if t not in self.tasks]
        if unknown or (self.dense_by_default and not self.dense_reward):
            raise DomainError(f"{where}: dense_by_default names "
                              + (f"unknown tasks {unknown}" if unknown else "tasks of a domain without dense_reward"))
        object.__setattr__(self, "dense_by_default", MappingProxyType(
            {task: bool(dense) for task, dense in self.dense_by_default.items()}))
        if self.known_reward is not None and not callable(self.known_reward):
            raise DomainError(f"{where}: known_reward must be None or a callable known_reward(task, dense_reward)")
        if self.exact_world is not None and self.exact_world not in EXACT_WORLDS:
            raise DomainError(f"{where}: exact_world must be None or one of {', '.join(EXACT_WORLDS)}, "
                              f"got {self.exact_world!r}")

    def _check_spec(self, spec: object) -> EnvSpec:
        where = f"domain '{self.name}'"
        if not isinstance(spec, EnvSpec):
            raise DomainError(f"{where}: its spec callable returned {type(spec).__name__}, not an EnvSpec")
        if spec.domain != self.name:
            raise DomainError(f"{where}: its EnvSpec names domain '{spec.domain}'; use "
                              f"EnvSpec('{self.name}', obs_dim, action_dim, discrete)")
        for key in ("obs_dim", "action_dim"):
            value = getattr(spec, key)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise DomainError(f"{where}: EnvSpec.{key} must be an int >= 1, got {value!r}")
        return spec

    def env_spec(self) -> EnvSpec:
        """The domain's :class:`EnvSpec`, computed on first use if :attr:`spec` is a callable."""
        if isinstance(self.spec, EnvSpec):
            return self.spec
        if "spec" not in self._cache:
            self._cache["spec"] = self._check_spec(self.spec())
        return self._cache["spec"]

    def task_description(self, task: str) -> str:
        """The one line of a task (KeyError for an unknown one)."""
        return self.tasks[task]


class ActionScaler:
    """Maps drago's actions in [-1, 1] onto a Box's bounds, dimension by dimension.

    A dimension with finite bounds below ``1e6`` in size is rescaled affinely; one without (dm_control's
    LQR says +-1e10) gets the clipped action unchanged.
    """

    def __init__(self, low: np.ndarray, high: np.ndarray, dtype: Any = np.float32) -> None:
        self.shape = np.shape(low)
        self.low = np.asarray(low, dtype=np.float64).ravel()
        self.high = np.asarray(high, dtype=np.float64).ravel()
        self.dtype = dtype
        self.bounded = np.isfinite(self.low) & np.isfinite(self.high) & (np.abs(self.low) < 1e6) & (
            np.abs(self.high) < 1e6)
        self.identity = bool(np.all(~self.bounded | ((self.low == -1) & (self.high == 1))))

    @property
    def size(self) -> int:
        return int(self.low.size)

    def __call__(self, action: Any) -> np.ndarray:
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(-1), -1.0, 1.0)
        if a.size != self.size:
            raise ValueError(f"expected an action of {self.size} numbers, got {a.size}")
        if not self.identity:
            scaled = self.low + (a + 1.0) * 0.5 * (self.high - self.low)
            a = np.where(self.bounded, scaled, a)
        return a.reshape(self.shape).astype(self.dtype)
