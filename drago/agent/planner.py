"""Model-predictive control with the cross-entropy method (spec §2.5).

Two variants share the trajectory evaluation: a Gaussian CEM with momentum and warm start for
continuous actions, and a categorical CEM over one-hot action sequences for the grid.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from drago.agent.networks import TaskHeads, WorldModel

# Multiplies non-negative predicted rewards at predicted next states (DRAGO's reviewer count bonus).
RewardBonus = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class PlanSettings:
    horizon: int
    iterations: int
    num_samples: int
    num_elites: int
    num_policy_trajectories: int
    temperature: float
    momentum: float
    discount: float
    use_q: bool
    policy_std: float
    min_std: float  # current CEM std floor (continuous only)
    max_std: float
    elite_selection: str  # "sample" or "argmax"


def imagine_step(world_model: WorldModel, heads: TaskHeads, z: torch.Tensor,
                 action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(predicted reward r(z, a), predicted next latent d(z, a)): one step of a trajectory's evaluation."""
    return heads.predict_reward(z, action), world_model(z, action)


def terminal_value(heads: TaskHeads, z: torch.Tensor, policy_std: float) -> torch.Tensor:
    """min(Q1, Q2)(z, pi(z, std)): the value of a trajectory's last latent."""
    return heads.q_values(z, heads.act(z, policy_std)).min(0).values


@dataclass(frozen=True)
class Evaluator:
    """The two functions a trajectory's evaluation calls; the agent swaps in compiled versions.

    One step is compiled rather than the whole horizon loop: the planning horizon grows with the
    schedule (1 -> H), and a compiled loop would be recompiled for every horizon.
    """

    step: Callable[..., tuple[torch.Tensor, torch.Tensor]] = imagine_step
    terminal: Callable[..., torch.Tensor] = terminal_value


EAGER = Evaluator()


@torch.no_grad()
def trajectory_returns(world_model: WorldModel, heads: TaskHeads, z0: torch.Tensor, actions: torch.Tensor,
                       discount: float, use_q: bool, policy_std: float,
                       bonus: RewardBonus | None = None, evaluator: Evaluator = EAGER) -> torch.Tensor:
    """G = sum_t gamma^t r_t + gamma^h min Q(z_h, pi(z_h)) for each of N action sequences.

    Args:
        z0: (n_z,) or (N, n_z) start latent.
        actions: (h, N, n_a) action sequences.
    """
    horizon, count = actions.shape[:2]
    z = z0.expand(count, -1) if z0.dim() == 1 else z0
    total = z.new_zeros(count)
    scale = 1.0
    for t in range(horizon):
        reward, z = evaluator.step(world_model, heads, z, actions[t])
        if bonus is not None:
            reward = torch.where(reward >= 0, reward * bonus(z), reward)
        total = total + scale * reward
        scale *= discount
    if use_q:
        total = total + scale * evaluator.terminal(heads, z, policy_std)
    return torch.nan_to_num(total, nan=0.0)


@torch.no_grad()
def policy_trajectories(world_model: WorldModel, heads: TaskHeads, z0: torch.Tensor, count: int, horizon: int,
                        policy_std: float, deterministic: bool) -> torch.Tensor:
    """(h, count, n_a) action sequences obtained by rolling the policy through the model."""
    z = z0.expand(count, -1)
    out = []
    for _ in range(horizon):
        action = heads.act(z, policy_std, deterministic=deterministic)
        out.append(action)
        z = world_model(z, action)
    return torch.stack(out)


def _policy_prior(world_model: WorldModel, heads: TaskHeads, z0: torch.Tensor, s: PlanSettings,
                  deterministic: bool) -> torch.Tensor | None:
    """The policy's own trajectories, added to every CEM iteration's samples (``mixture_coef``)."""
    if s.num_policy_trajectories == 0:
        return None
    return policy_trajectories(world_model, heads, z0, s.num_policy_trajectories, s.horizon, s.policy_std,
                               deterministic)


def _elite_weights(returns: torch.Tensor, num_elites: int, temperature: float) -> tuple[torch.Tensor, torch.Tensor]:
    elite_returns, elite_idx = torch.topk(returns, num_elites)
    weights = torch.softmax(temperature * elite_returns, dim=0)  # = exp(T(G - max G)) normalised
    return weights, elite_idx


def _chosen_elite(elites: torch.Tensor, weights: torch.Tensor, selection: str) -> torch.Tensor:
    """The first action of one elite sequence: the best, or one drawn in proportion to its weight.

    Indexed with a one-element tensor, so a GPU never waits for the host to read the choice.
    """
    choice = weights.argmax().view(1) if selection == "argmax" else torch.multinomial(weights, 1)
    return elites[0].index_select(0, choice)[0]


@torch.no_grad()
def plan_discrete(world_model: WorldModel, heads: TaskHeads, obs: torch.Tensor, s: PlanSettings,
                  eval_mode: bool, bonus: RewardBonus | None = None, evaluator: Evaluator = EAGER) -> torch.Tensor:
    """Categorical CEM over one-hot sequences; returns the first one-hot action of a chosen elite.

    The categorical mean starts uniform (1/|A|; the official code's 1/h is a bug, spec §7.2.18).
    Exploration comes from CEM sampling and the stochastic elite choice; there is no action noise.
    """
    n_a = world_model.action_dim
    z0 = world_model.encode(obs)
    pi_actions = _policy_prior(world_model, heads, z0, s, deterministic=eval_mode)
    mean = obs.new_full((s.horizon, n_a), 1.0 / n_a)
    for _ in range(s.iterations):
        idx = torch.multinomial(mean, s.num_samples, replacement=True)  # (h, num_samples)
        actions = F.one_hot(idx, n_a).to(obs.dtype)
        if pi_actions is not None:
            actions = torch.cat((actions, pi_actions), dim=1)
        returns = trajectory_returns(world_model, heads, z0, actions, s.discount, s.use_q, s.policy_std, bonus,
                                     evaluator)
        weights, elite_idx = _elite_weights(returns, s.num_elites, s.temperature)
        elites = actions[:, elite_idx]  # (h, k, n_a)
        refit = (weights[None, :, None] * elites).sum(1)
        mean = s.momentum * mean + (1 - s.momentum) * refit
    return _chosen_elite(elites, weights, s.elite_selection)


@torch.no_grad()
def plan_continuous(world_model: WorldModel, heads: TaskHeads, obs: torch.Tensor, s: PlanSettings,
                    eval_mode: bool, warm_mean: torch.Tensor | None, bonus: RewardBonus | None = None,
                    evaluator: Evaluator = EAGER) -> tuple[torch.Tensor, torch.Tensor]:
    """Gaussian CEM with momentum; returns (action, mean to warm-start the next step's plan).

    The executed action is clipped to [-1, 1] after exploration noise, so the buffer stores what the
    simulator executes (the official code stores unclipped actions, spec §7.2.22).
    """
    n_a = world_model.action_dim
    z0 = world_model.encode(obs)
    # TD-MPC keeps the continuous policy's noise even when evaluating.
    pi_actions = _policy_prior(world_model, heads, z0, s, deterministic=False)
    mean = obs.new_zeros((s.horizon, n_a))
    std = obs.new_full((s.horizon, n_a), s.max_std)
    if warm_mean is not None:
        shift = min(s.horizon - 1, warm_mean.shape[0] - 1)
        mean[:shift] = warm_mean[1:shift + 1]
    for _ in range(s.iterations):
        noise = torch.randn(s.horizon, s.num_samples, n_a, dtype=obs.dtype, device=obs.device)
        actions = (mean[:, None] + std[:, None] * noise).clamp(-1, 1)
        if pi_actions is not None:
            actions = torch.cat((actions, pi_actions), dim=1)
        returns = trajectory_returns(world_model, heads, z0, actions, s.discount, s.use_q, s.policy_std, bonus,
                                     evaluator)
        weights, elite_idx = _elite_weights(returns, s.num_elites, s.temperature)
        elites = actions[:, elite_idx]
        refit_mean = (weights[None, :, None] * elites).sum(1)
        refit_std = (weights[None, :, None] * (elites - refit_mean[:, None]).pow(2)).sum(1).sqrt()
        mean = s.momentum * mean + (1 - s.momentum) * refit_mean
        std = refit_std.clamp(s.min_std, s.max_std)
    action = _chosen_elite(elites, weights, s.elite_selection)
    if not eval_mode:
        action = action + std[0] * torch.randn_like(action)
    return action.clamp(-1, 1), mean
