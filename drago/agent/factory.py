"""The agent a run's ``agent.kind`` asks for: the built-in kinds, TD-MPC (the paper's) and PETS (the paper's
Appendix E), registered as :class:`~drago.agent.protocol.AgentKind` objects, and the calls that build a run's
parts through its kind: the world model each task carries, its optimizer, an agent (learner or DRAGO's
reviewer) over it, and the length of the replay sequences it learns from (docs: Methods, PETS). The trainer,
the continual methods and the checkpoint loader build through these, so none of them tests the kind.
"""

from __future__ import annotations

import torch
from torch import nn

from drago.agent.agent import Agent
from drago.agent.networks import build_world_model as build_tdmpc_world_model
from drago.agent.pets import (
    PetsAgent,
    PetsConfig,
    PetsPlanSettings,
    PetsWorldModel,
    RewardFn,
    RewardHead,
    make_optimizer,
)
from drago.agent.protocol import (PETS_CAPABILITIES, TDMPC_CAPABILITIES, AgentKind, ContinualAgent, get_agent_kind,
                                  register_agent_kind)
from drago.config import Config
from drago.envs import EnvSpec, get_domain

__all__ = ["PETS", "TDMPC", "build_agent", "build_world_model", "build_world_optimizer", "pets_config", "replay_horizon"]


def pets_config(cfg: Config) -> PetsConfig:
    """The PETS agent's settings from ``cfg.agent.pets`` and the shared ``agent.lr``. The ensemble predicts states
    only: rewards are learned by each agent's own head (or given), so the ensemble can be carried across tasks
    (docs: Methods, PETS)."""
    a, p = cfg.agent, cfg.agent.pets
    plan = PetsPlanSettings(horizon=p.horizon, iterations=p.iterations, population=p.population, elites=p.elites,
                            particles=p.particles, momentum=p.momentum, propagation=p.propagation)
    return PetsConfig(members=p.members, hidden=p.hidden, layers=p.layers, lr=a.lr,
                      predict_reward=False, plan=plan, random_action_probs=a.random_action_probs)


# ---- TD-MPC (the paper's agent) ---------------------------------------------------------------------
def _tdmpc_world_optimizer(cfg: Config, world_model: nn.Module) -> torch.optim.Optimizer:
    return torch.optim.Adam(world_model.dynamics.parameters(), lr=cfg.agent.lr)


def _tdmpc_agent(cfg: Config, spec: EnvSpec, world_model: nn.Module, world_optimizer: torch.optim.Optimizer | None,
                 task: str | None = None, reviewer: bool = False) -> Agent:
    return Agent(world_model, world_optimizer, cfg.agent, spec.discrete, reviewer=reviewer)


TDMPC = register_agent_kind(AgentKind(
    name="tdmpc", description="TD-MPC: latent dynamics, reward, policy and twin Q heads, CEM planning (the paper's)",
    capabilities=TDMPC_CAPABILITIES, build_world_model=build_tdmpc_world_model,
    build_world_optimizer=_tdmpc_world_optimizer, build_agent=_tdmpc_agent,
    replay_horizon=lambda cfg: cfg.agent.tdmpc.horizon))


# ---- PETS (paper Appendix E) -----------------------------------------------------------------------------
def _pets_world_model(cfg: Config, spec: EnvSpec, device: torch.device | str = "cpu") -> nn.Module:
    ensemble = pets_config(cfg).build_world_model(spec.obs_dim, spec.action_dim, device)
    # The grid's observations lie in [-1, 1], where TD-MPC's dynamics end in tanh (paper Appendix A).
    return PetsWorldModel(ensemble, (-1.0, 1.0) if spec.discrete else None)


def _known_reward(cfg: Config, task: str) -> RewardFn:
    reward = get_domain(cfg.env.domain).known_reward(task, cfg.env.dense_reward)
    return lambda obs, action, next_obs: reward(obs, action, next_obs).to(obs.dtype)


def _pets_agent(cfg: Config, spec: EnvSpec, world_model: nn.Module, world_optimizer: torch.optim.Optimizer | None,
                task: str | None = None, reviewer: bool = False) -> PetsAgent:
    """A PETS agent gets a fresh reward head of its own, as a TD-MPC agent gets fresh heads; with
    ``agent.pets.reward=known`` the learner plans on the task's true reward instead, while the reviewer,
    whose intrinsic reward exists only as labels of its data, always learns its own."""
    settings = pets_config(cfg)
    if cfg.agent.pets.reward == "known" and not reviewer:
        if task is None:
            raise ValueError("a PETS learner with agent.pets.reward=known needs its task")
        return PetsAgent(world_model, world_optimizer, settings, spec.discrete, known_reward=_known_reward(cfg, task))
    device = next(world_model.parameters()).device
    head = RewardHead(spec.obs_dim, spec.action_dim, settings.hidden).to(device)
    return PetsAgent(world_model, world_optimizer, settings, spec.discrete, reward_head=head)


PETS = register_agent_kind(AgentKind(
    name="pets", description="PETS: a probabilistic ensemble with trajectory sampling and CEM (paper Appendix E)",
    capabilities=PETS_CAPABILITIES, build_world_model=_pets_world_model,
    build_world_optimizer=lambda cfg, world_model: make_optimizer(world_model.ensemble, cfg.agent.lr),
    build_agent=_pets_agent,
    # Single transitions: pairs (H = 1, the buffer's least) whose two transitions both train it.
    replay_horizon=lambda cfg: 1, told_reward=lambda cfg: cfg.agent.pets.reward == "known"))


# ---- what the trainer, the methods and the checkpoint loader call ---------------------------------------
def build_world_model(cfg: Config, spec: EnvSpec, device: torch.device | str = "cpu") -> nn.Module:
    """The world model a run of ``cfg`` trains and its checkpoints hold, as its ``agent.kind`` builds it."""
    return get_agent_kind(cfg.agent.kind).build_world_model(cfg, spec, device)


def build_world_optimizer(cfg: Config, world_model: nn.Module) -> torch.optim.Optimizer:
    """The one optimizer of a task's world model, shared by the agents that train it (DRAGO's two)."""
    return get_agent_kind(cfg.agent.kind).build_world_optimizer(cfg, world_model)


def build_agent(cfg: Config, spec: EnvSpec, world_model: nn.Module, world_optimizer: torch.optim.Optimizer | None,
                task: str | None = None, reviewer: bool = False) -> ContinualAgent:
    """A learner (or with ``reviewer`` DRAGO's reviewer) of task ``task`` over ``world_model``."""
    return get_agent_kind(cfg.agent.kind).build_agent(cfg, spec, world_model, world_optimizer, task, reviewer)


def replay_horizon(cfg: Config) -> int:
    """H of the replay buffers' (H+1)-step sequences the run's agent kind learns from."""
    return get_agent_kind(cfg.agent.kind).replay_horizon(cfg)
