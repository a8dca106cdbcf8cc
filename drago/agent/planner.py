"""Model-predictive control with the cross-entropy method (paper §2; docs: Design, the agent).

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
    """(h, E, P, n_a): the policy's own trajectories from each of the E start latents, added to every CEM
    iteration's samples (``mixture_coef``)."""
    if s.num_policy_trajectories == 0:
        return None
    count = s.num_policy_trajectories
    starts = z0.repeat_interleave(count, dim=0)
    trajectories = policy_trajectories(world_model, heads, starts, len(starts), s.horizon, s.policy_std, deterministic)
    return trajectories.view(s.horizon, len(z0), count, -1)


def _batched_returns(world_model: WorldModel, heads: TaskHeads, z0: torch.Tensor, actions: torch.Tensor,
                     s: PlanSettings, bonus: RewardBonus | None, evaluator: Evaluator) -> torch.Tensor:
    """(E, M) returns of the (h, E, M, n_a) candidate sequences, the E problems evaluated as one batch."""
    horizon, problems, count = actions.shape[:3]
    starts = z0[:, None].expand(problems, count, -1).reshape(problems * count, -1)
    returns = trajectory_returns(world_model, heads, starts, actions.reshape(horizon, problems * count, -1),
                                 s.discount, s.use_q, s.policy_std, bonus, evaluator)
    return returns.view(problems, count)


def _elites(actions: torch.Tensor, returns: torch.Tensor, num_elites: int,
            temperature: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(elite sequences (h, E, k, n_a), their weights (E, k)): each problem's k best, weighted by
    exp(T(G - max G)) normalised."""
    elite_returns, elite_idx = torch.topk(returns, num_elites, dim=-1)
    weights = torch.softmax(temperature * elite_returns, dim=-1)
    problems = torch.arange(len(returns), device=returns.device)[:, None]
    return actions[:, problems, elite_idx], weights


def _chosen_elite(elites: torch.Tensor, weights: torch.Tensor, selection: str) -> torch.Tensor:
    """(E, n_a): each problem's first action of one elite sequence, the best or one drawn in proportion
    to its weight.

    Gathered with index tensors, so a GPU never waits for the host to read the choice.
    """
    choice = weights.argmax(-1, keepdim=True) if selection == "argmax" else torch.multinomial(weights, 1)
    first = elites[0]  # (E, k, n_a)
    return first.gather(1, choice[:, :, None].expand(-1, 1, first.shape[-1]))[:, 0]


def _as_problems(obs: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """(E, n) observations and whether a single (n,) observation was given."""
    if obs.dim() == 1:
        return obs[None], True
    if obs.dim() != 2:
        raise ValueError(f"observations must have shape (n,) or (E, n), got {tuple(obs.shape)}")
    return obs, False


@torch.no_grad()
def plan_discrete(world_model: WorldModel, heads: TaskHeads, obs: torch.Tensor, s: PlanSettings,
                  eval_mode: bool, bonus: RewardBonus | None = None, evaluator: Evaluator = EAGER) -> torch.Tensor:
    """Categorical CEM over one-hot sequences; returns the first one-hot action of a chosen elite.

    ``obs`` is one observation (n,) or E independent ones (E, n), e.g. E evaluation episodes played side
    by side: their planning problems run as one batch and the result is (n_a,) or (E, n_a). With E = 1 the
    draws and the arithmetic are those of a single problem, so batching never changes a training run.

    The categorical mean starts uniform (1/|A|; the official code's 1/h is a bug, docs: Design, departures from the official code).
    Exploration comes from CEM sampling and the stochastic elite choice; there is no action noise.
    """
    obs, single = _as_problems(obs)
    problems, n_a = len(obs), world_model.action_dim
    z0 = world_model.encode(obs)
    pi_actions = _policy_prior(world_model, heads, z0, s, deterministic=eval_mode)
    mean = obs.new_full((s.horizon, problems, n_a), 1.0 / n_a)
    for _ in range(s.iterations):
        idx = torch.multinomial(mean.view(-1, n_a), s.num_samples, replacement=True)  # (h * E, num_samples)
        actions = F.one_hot(idx, n_a).to(obs.dtype).view(s.horizon, problems, s.num_samples, n_a)
        if pi_actions is not None:
            actions = torch.cat((actions, pi_actions), dim=2)
        returns = _batched_returns(world_model, heads, z0, actions, s, bonus, evaluator)
        elites, weights = _elites(actions, returns, s.num_elites, s.temperature)
        refit = (weights[None, :, :, None] * elites).sum(2)
        mean = s.momentum * mean + (1 - s.momentum) * refit
    action = _chosen_elite(elites, weights, s.elite_selection)
    return action[0] if single else action


@torch.no_grad()
def plan_continuous(world_model: WorldModel, heads: TaskHeads, obs: torch.Tensor, s: PlanSettings,
                    eval_mode: bool, warm_mean: torch.Tensor | None, bonus: RewardBonus | None = None,
                    evaluator: Evaluator = EAGER) -> tuple[torch.Tensor, torch.Tensor]:
    """Gaussian CEM with momentum; returns (action, mean to warm-start the next step's plan).

    ``obs`` is one observation (n,) or E independent ones (E, n), planned as one batch (see
    :func:`plan_discrete`); the action is then (n_a,) or (E, n_a) and the mean (h, n_a) or (h, E, n_a),
    the shape ``warm_mean`` is expected in.

    The executed action is clipped to [-1, 1] after exploration noise, so the buffer stores what the
    simulator executes (the official code stores unclipped actions, docs: Design, departures from the official code).
    """
    obs, single = _as_problems(obs)
    problems, n_a = len(obs), world_model.action_dim
    z0 = world_model.encode(obs)
    # TD-MPC keeps the continuous policy's noise even when evaluating.
    pi_actions = _policy_prior(world_model, heads, z0, s, deterministic=False)
    mean = obs.new_zeros((s.horizon, problems, n_a))
    std = obs.new_full((s.horizon, problems, n_a), s.max_std)
    if warm_mean is not None:
        warm_mean = warm_mean[:, None] if single else warm_mean
        shift = min(s.horizon - 1, warm_mean.shape[0] - 1)
        mean[:shift] = warm_mean[1:shift + 1]
    for _ in range(s.iterations):
        noise = torch.randn(s.horizon, problems, s.num_samples, n_a, dtype=obs.dtype, device=obs.device)
        actions = (mean[:, :, None] + std[:, :, None] * noise).clamp(-1, 1)
        if pi_actions is not None:
            actions = torch.cat((actions, pi_actions), dim=2)
        returns = _batched_returns(world_model, heads, z0, actions, s, bonus, evaluator)
        elites, weights = _elites(actions, returns, s.num_elites, s.temperature)
        refit_mean = (weights[None, :, :, None] * elites).sum(2)
        refit_std = (weights[None, :, :, None] * (elites - refit_mean[:, :, None]).pow(2)).sum(2).sqrt()
        mean = s.momentum * mean + (1 - s.momentum) * refit_mean
        std = refit_std.clamp(s.min_std, s.max_std)
    action = _chosen_elite(elites, weights, s.elite_selection)
    if not eval_mode:
        action = action + std[0] * torch.randn_like(action)
    action = action.clamp(-1, 1)
    return (action[0], mean[:, 0]) if single else (action, mean)
