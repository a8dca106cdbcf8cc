"""What drago asks of an agent, and what an agent kind declares it can do (docs: design, "The agent protocol").

The trainer, the continual methods, the evaluations and the reports reach an agent only through
:class:`ContinualAgent` and ask :class:`AgentCapabilities` where kinds differ; none of them tests a kind's
name. An :class:`AgentKind` bundles a kind's builders with its capabilities and is registered under the
name ``agent.kind`` takes: TD-MPC and PETS by :mod:`drago.agent.factory`, others with
:func:`register_agent_kind` or through a package's ``drago.agents`` entry point.

This module imports nothing heavier than torch's types, so the speed settings can ask a kind's
capabilities without building one.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import drago.config as _config
from drago.config import ConfigError
from drago.plugins import PluginProblem, load_entry_points

if TYPE_CHECKING:
    import numpy as np
    import torch
    from torch import nn

    from drago.config import Config
    from drago.envs import EnvSpec

__all__ = ["ENTRY_POINT_GROUP", "PETS_CAPABILITIES", "TDMPC_CAPABILITIES", "AgentCapabilities", "AgentKind",
           "ContinualAgent", "ContinualWorldModel", "agent_kinds", "capabilities_of", "get_agent_kind", "plugin_problems",
           "register_agent_kind", "unregister_agent_kind"]

ENTRY_POINT_GROUP = "drago.agents"
_NAME = re.compile(r"[a-z0-9][a-z0-9_-]*")


@dataclass(frozen=True, kw_only=True)
class AgentCapabilities:
    """What an agent kind can do, for the code that would otherwise test its name.

    Attributes:
        value_function: A learned value whose TD target a bonus can enter (the curiosity method needs it).
        task_heads: Reward, policy and value heads apart from the world model, planned with it (the component
            probes measure and swap them).
        shared_rollout: ``rollout(obs, actions)`` gives latents that two updates of one batch can share, and
            ``update(..., latents=...)`` takes them (DRAGO's learner and reviewer share one rollout).
        sequence_loss: The world model learns from H-step sequences weighted by ``agent.tdmpc.consistency_coef``
            (replayed old transitions are weighted to match); without it, from single transitions of weight 1.
        reduced_precision: Honours ``agent.tdmpc.precision`` and ``agent.tdmpc.compile``; without it the kind runs in
            float32, eager.
        plan_schedules: Its planner's horizon and CEM std floor follow schedules over updates (the
            pre-rollout's ``code`` planning resets the floor).
    """

    value_function: bool = False
    task_heads: bool = False
    shared_rollout: bool = False
    sequence_loss: bool = False
    reduced_precision: bool = False
    plan_schedules: bool = False


TDMPC_CAPABILITIES = AgentCapabilities(value_function=True, task_heads=True, shared_rollout=True,
                                       sequence_loss=True, reduced_precision=True, plan_schedules=True)
PETS_CAPABILITIES = AgentCapabilities()


@runtime_checkable
class ContinualWorldModel(Protocol):
    """The world model a task carries, as the methods and evaluations read it (``nn.Module`` besides).

    ``encode`` maps observations to the model's state (the identity where it has no latent space);
    ``forward(z, a)`` is the next state as the planner sees it; ``raw_next(z, a)`` the prediction before any
    final squash or clamp (synthetic rehearsal pulls it towards the frozen old model's, paper §3.1). A model
    may add ``transition_loss(obs, action, next_obs)``, its own objective on single transitions, which
    replay and EWC then use instead of a one-step consistency loss.
    """

    obs_dim: int
    action_dim: int

    def encode(self, obs: torch.Tensor) -> torch.Tensor: ...

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor: ...

    def raw_next(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor: ...


@runtime_checkable
class ContinualAgent(Protocol):
    """The surface of a learner (or DRAGO's reviewer) over a world model that drago uses.

    A task's world model and its optimizer are handed in and saved by their owner (the trainer); the agent
    owns what it learns on top (heads, a reward head) and its planner's state.
    """

    world_model: nn.Module
    device: torch.device
    capabilities: AgentCapabilities

    def autocast(self) -> AbstractContextManager[Any]:
        """The context of the agent's forward passes (a reduced precision, or nothing)."""

    def act(self, obs: np.ndarray, step: int, eval_mode: bool, first_step: bool,
            bonus: Callable[[torch.Tensor], torch.Tensor] | None = None) -> np.ndarray:
        """One action for an observation (n,), or one per row of (B, n); ``bonus`` adds to planned rewards."""

    def random_action(self, rng: np.random.Generator) -> np.ndarray:
        """An action of the seed phase."""

    def update(self, batch: Any, step: int, train_world_model: bool = True, policy_rows: int | None = None,
               world_model_loss: Callable[[], torch.Tensor] | None = None,
               **options: Any) -> dict[str, torch.Tensor]:
        """One gradient step on a replay batch; metrics as tensors, with the rows' new ``priority``.

        ``options`` are those a capability adds (``latents`` with ``shared_rollout``, ``curiosity_coef`` with
        ``value_function``); a caller passes them only to a kind that declares the capability.
        """

    def task_state(self) -> dict[str, Any]:
        """What a task checkpoint keeps of the learner (for pre-rollouts, held-out sets and the probes)."""

    def load_task_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`task_state` from a task checkpoint's dictionary."""

    def trained_modules(self) -> dict[str, nn.Module]:
        """The agent's own trained networks by name, checked for non-finite weights."""

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume mid-task (optimizers included)."""

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""


@dataclass(frozen=True, kw_only=True)
class AgentKind:
    """An agent kind: its name, what it can do, and how to build its parts from a run's config.

    Attributes:
        name: What ``agent.kind`` takes.
        description: One line for ``drago list``.
        capabilities: What the kind can do.
        build_world_model: ``(cfg, spec, device) -> nn.Module``: the world model a task carries.
        build_world_optimizer: ``(cfg, world_model) -> Optimizer``: its one optimizer, shared by the agents
            that train it.
        build_agent: ``(cfg, spec, world_model, world_optimizer, task, reviewer) -> ContinualAgent``: a learner of
            ``task`` (or with ``reviewer`` DRAGO's reviewer).
        replay_horizon: ``(cfg) -> int``: H of the replay buffers' (H+1)-step sequences (1: transition pairs).
        told_reward: ``(cfg) -> bool``: the learner plans with the task's true reward and learns none (a method
            that changes the rewards it learns from cannot run then).
    """

    name: str
    description: str
    capabilities: AgentCapabilities
    build_world_model: Callable[[Config, EnvSpec, Any], nn.Module]
    build_world_optimizer: Callable[[Config, nn.Module], torch.optim.Optimizer]
    build_agent: Callable[..., ContinualAgent]
    replay_horizon: Callable[[Config], int]
    told_reward: Callable[[Config], bool] = lambda cfg: False


_KINDS: dict[str, AgentKind] = {}
_BUILTIN = {"tdmpc": TDMPC_CAPABILITIES, "pets": PETS_CAPABILITIES}
_problems: list[PluginProblem] = []
_plugins_loaded = False


def register_agent_kind(kind: AgentKind, replace: bool = False) -> AgentKind:
    """Register an agent kind under ``kind.name``, so that ``agent.kind=NAME`` runs it.

    Raises:
        ConfigError: a bad name, not an :class:`AgentKind`, or a name another kind holds (``replace=True``
            takes it over).
    """
    if not isinstance(kind, AgentKind):
        raise ConfigError(f"register_agent_kind needs a drago.AgentKind, got {type(kind).__name__}")
    if not _NAME.fullmatch(kind.name):
        raise ConfigError(f"agent kind name {kind.name!r} must be lowercase letters, digits, '-' and '_'")
    if kind.name in _KINDS and _KINDS[kind.name] is not kind and not replace:
        raise ConfigError(f"agent kind '{kind.name}' is already registered; choose another name or pass replace=True")
    _KINDS[kind.name] = kind
    _config.CHOICES["agent.kind"] = tuple(dict.fromkeys([*_config.CHOICES["agent.kind"], kind.name]))
    return kind


def unregister_agent_kind(name: str) -> None:
    """Remove a kind registered from Python (tests); the built-in kinds stay."""
    if name in _BUILTIN:
        raise ConfigError(f"agent kind '{name}' is built in and cannot be removed")
    _KINDS.pop(name, None)
    _config.CHOICES["agent.kind"] = tuple(k for k in _config.CHOICES["agent.kind"] if k != name)


def load_plugins() -> None:
    """Register the agent kinds of installed packages (entry point group ``drago.agents``), once.

    An entry point names an :class:`AgentKind` (or a module whose import registers kinds); one that fails is
    announced in one line and skipped.
    """
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True

    def register(entry: Any) -> None:
        loaded = entry.load()
        if isinstance(loaded, AgentKind):
            register_agent_kind(loaded)
        elif entry.name not in _KINDS:
            raise ConfigError(f"it loaded {entry.value} but registered no agent kind named '{entry.name}'")

    _problems.extend(load_entry_points(ENTRY_POINT_GROUP, "agent kind", register, plain_errors=(ConfigError,)))


def plugin_problems() -> tuple[PluginProblem, ...]:
    load_plugins()
    return tuple(_problems)


def agent_kinds() -> dict[str, AgentKind]:
    """Every registered kind by name, built-in first."""
    load_plugins()
    return dict(_KINDS)


def get_agent_kind(name: str) -> AgentKind:
    """The kind ``agent.kind=name`` runs (ConfigError naming the valid ones)."""
    load_plugins()
    if name not in _KINDS:
        raise ConfigError(f"unknown agent.kind '{name}'; valid kinds: {', '.join(_KINDS)}")
    return _KINDS[name]


def capabilities_of(name: str) -> AgentCapabilities:
    """A kind's capabilities: those it was registered with, or a built-in kind's before its builders register."""
    if name in _KINDS:
        return _KINDS[name].capabilities
    return _BUILTIN[name] if name in _BUILTIN else get_agent_kind(name).capabilities


# An agent.kind=NAME may be a plug-in's kind: the config looks after the plug-ins load.
_config.load_agent_plugins = load_plugins
