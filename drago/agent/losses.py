"""The TD-MPC training losses of paper §2; docs: Design, the agent as functions of modules and a batch.

Only the dynamics rollout is sequential; the reward head, the critics and the TD targets see detached
inputs, so each of them is evaluated in one batched call over all H steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from drago.agent.networks import TaskHeads, WorldModel

# Added inside every log of a squared error: an exact prediction must give a large score, not inf.
LOG_EPS = 1e-10
# Per-sample loss terms are clamped before weighting, as in TD-MPC.
LOSS_CLAMP = 1e4


@dataclass
class ModelLosses:
    """Per-sample losses (B,) and the by-products the update needs."""

    consistency: torch.Tensor
    reward: torch.Tensor
    value: torch.Tensor
    total: torch.Tensor  # coef-weighted, clamped sum per sample
    priority: torch.Tensor  # new PER priorities (before the +1e-6)
    latents: torch.Tensor  # (H+1, B, n_z) detached z_0..z_H for the policy update
    prediction_score: torch.Tensor  # scalar: mean over batch of (1/H) sum_t -log mse_t; 0 if no consistency


def prediction_error(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the last (feature) dimension."""
    return (predicted - target).pow(2).mean(-1)


def prediction_score(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """-log(mean squared error): the code's "prediction score", higher is better."""
    return -torch.log(prediction_error(predicted, target) + LOG_EPS)


def rho_weights(rho: float, steps: int, like: torch.Tensor) -> torch.Tensor:
    return rho ** torch.arange(steps, dtype=like.dtype, device=like.device)


def rollout(world_model: WorldModel, obs: torch.Tensor, actions: torch.Tensor, horizon: int) -> torch.Tensor:
    """(H+1, B, n_z) latents z_0 = h(s_0), z_{t+1} = d(z_t, a_t): the open-loop model rollout of paper §2; docs: Design, the agent.

    Built with a graph when gradients are enabled, so the consistency loss can train the dynamics.
    """
    z = world_model.encode(obs)
    latents = [z]
    for t in range(horizon):
        z = world_model(z, actions[t])
        latents.append(z)
    return torch.stack(latents)


def model_losses(world_model: WorldModel, heads: TaskHeads, obs: torch.Tensor, actions: torch.Tensor,
                 rewards: torch.Tensor, next_obs: torch.Tensor, *, horizon: int, rho: float, discount: float,
                 policy_std: float, consistency_coef: float, reward_coef: float, value_coef: float,
                 first_step_qr_only: bool, train_world_model: bool, reviewer_priority: bool = False,
                 curiosity_coef: float = 0.0, latents: torch.Tensor | None = None) -> ModelLosses:
    """Consistency, reward and value losses of one agent on one batch (paper §2; docs: Design, the agent steps 1-3).

    Args:
        obs: (B, n) start observations s_0.
        actions, rewards, next_obs: (>=H, B, ...) sequences; only t < H is used.
        train_world_model: compute the consistency loss (and the prediction score). When false the
            dynamics rollout runs without a graph: the latents still feed the heads, but no world-model
            gradient is built for a loss that would be zero (DRAGO's learner in tasks >= 2).
        reviewer_priority: use the reviewer's priority r + 2 + |TD errors| instead of |TD errors|.
        curiosity_coef: c in the TD target's reward r + c * e_t, with e_t the open-loop prediction error
            of the current model (paper §2; docs: Design, the agent; the curiosity baseline). The reward head still fits r.
        latents: the :func:`rollout` of these rows when the caller already has it (with a graph if
            ``train_world_model``): DRAGO rolls the world model once over reviewer and learner rows and
            hands each update its rows, since the learner's update does not change the world model.
    """
    if latents is None:
        with torch.set_grad_enabled(train_world_model and torch.is_grad_enabled()):
            latents = rollout(world_model, obs, actions, horizon)
    elif latents.shape[:2] != (horizon + 1, obs.shape[0]):
        raise ValueError(f"latents of shape {tuple(latents.shape)} do not match horizon {horizon} and "
                         f"batch {obs.shape[0]}")
    predicted = latents[1:]  # (H, B, n) with graph when training the world model
    targets = world_model.encode(next_obs[:horizon])
    rho_t = rho_weights(rho, horizon, obs)
    batch = obs.shape[0]

    if train_world_model:
        mse = prediction_error(predicted, targets)  # (H, B)
        consistency = (rho_t[:, None] * mse).sum(0)
        score = -torch.log(mse.detach() + LOG_EPS).sum(0).mean() / horizon
    else:
        consistency = obs.new_zeros(batch)
        score = obs.new_zeros(())

    z_in = latents[:horizon].detach()  # z_t for t < H (z_0 real, later ones imagined)
    step_actions = actions[:horizon]
    with torch.no_grad():
        next_z = targets.detach()
        next_pi = heads.act(next_z, policy_std)
        next_q = heads.q_values(next_z.flatten(0, 1), next_pi.flatten(0, 1), target=True).min(0).values
        td_reward = rewards[:horizon]
        if curiosity_coef:
            td_reward = td_reward + curiosity_coef * prediction_error(predicted.detach(), targets)
        td_target = td_reward + discount * next_q.view(horizon, batch)

    fitted = 1 if first_step_qr_only else horizon
    q_fit = heads.q_values(z_in[:fitted].flatten(0, 1), step_actions[:fitted].flatten(0, 1)).view(2, fitted, batch)
    reward_pred = heads.predict_reward(z_in[:fitted], step_actions[:fitted])
    reward_loss = (rho_t[:fitted, None] * (reward_pred - rewards[:fitted]).pow(2)).sum(0)
    value_loss = (rho_t[:fitted, None] * (q_fit - td_target[:fitted]).pow(2).sum(0)).sum(0)

    with torch.no_grad():
        if fitted == horizon:
            q_all = q_fit.detach()
        else:
            q_rest = heads.q_values(z_in[fitted:].flatten(0, 1), step_actions[fitted:].flatten(0, 1))
            q_all = torch.cat((q_fit.detach(), q_rest.view(2, horizon - fitted, batch)), dim=1)
        td_error = (q_all - td_target).abs().sum(0)  # (H, B)
        if reviewer_priority:
            # The reviewer's rewards lie in (-0.5, 1); +2 keeps every priority positive.
            td_error = td_error + rewards[:horizon] + 2.0
        priority = (rho_t[:, None] * td_error).sum(0)

    total = (consistency_coef * consistency.clamp(max=LOSS_CLAMP)
             + reward_coef * reward_loss.clamp(max=LOSS_CLAMP)
             + value_coef * value_loss.clamp(max=LOSS_CLAMP))
    return ModelLosses(consistency=consistency, reward=reward_loss, value=value_loss, total=total,
                       priority=priority, latents=latents.detach(), prediction_score=score)


def policy_loss(heads: TaskHeads, latents: torch.Tensor, rho: float, policy_std: float) -> torch.Tensor:
    """-sum_t rho^t mean(min(Q1, Q2)(z_t, pi(z_t))) over the stored latents z_0..z_H (paper §2; docs: Design, the agent step 6).

    The critics are evaluated but must not be updated by this loss: differentiate it with respect to
    the policy parameters only.
    """
    steps, batch = latents.shape[:2]
    actions = heads.act(latents, policy_std)
    q = heads.q_values(latents.flatten(0, 1), actions.flatten(0, 1)).min(0).values.view(steps, batch)
    return -(rho_weights(rho, steps, latents) * q.mean(-1)).sum()
