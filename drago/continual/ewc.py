"""Elastic weight consolidation on the world model (paper §4, the paper's EWC baseline).

At the end of every task the diagonal Fisher of the world model's consistency loss is estimated on that
task's data and added to the Fisher accumulated over the earlier tasks; the world model it ended with
becomes the anchor. During the next tasks the learner's world-model objective gets the quadratic
penalty ``method.ewc.coef / 2 * sum_i F_i (theta_i - theta*_i)^2``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol

import torch
from torch import nn

from drago.agent.losses import prediction_error, rho_weights
from drago.config import Config
from drago.continual.base import ContinualMethod, TaskState
from drago.envs import EnvSpec

ParamDict = dict[str, torch.Tensor]


class SequenceBatch(Protocol):
    """What the Fisher needs from a batch: a :class:`drago.agent.buffer.Batch` qualifies."""

    obs: torch.Tensor  # (B, n)
    actions: torch.Tensor  # (>=H, B, n_a)
    next_obs: torch.Tensor  # (>=H, B, n)


def trainable_parameters(world_model: nn.Module) -> dict[str, nn.Parameter]:
    """The world model's parameters that its optimizer trains, by name.

    The EMA target copy has ``requires_grad=False`` and is never regularised: it only follows the online
    dynamics.
    """
    return {name: p for name, p in world_model.named_parameters() if p.requires_grad}


def consistency_loss(world_model: nn.Module, obs: torch.Tensor, actions: torch.Tensor, next_obs: torch.Tensor,
                     horizon: int, rho: float) -> torch.Tensor:
    """Per-sample multi-step consistency loss of paper §2; docs: Design, the agent: ``sum_t rho^t mse(z_{t+1}, h(s_{t+1}))``.

    The rollout is open loop from ``z_0 = h(s_0)``, exactly as in the learner's update, so the Fisher
    measures the curvature of the loss the world model is actually trained on.

    Args:
        world_model: anything with ``encode(obs)`` and ``forward(z, a)`` (a :class:`WorldModel`).
        obs: (B, n) start observations.
        actions, next_obs: (>=H, B, ...) sequences; only the first ``horizon`` steps are used.
        horizon: H, the number of predicted steps.
        rho: temporal weight of the t-th term.

    Returns:
        (B,) losses with a graph to the world model's parameters.
    """
    z = world_model.encode(obs)
    predicted = []
    for t in range(horizon):
        z = world_model(z, actions[t])
        predicted.append(z)
    targets = world_model.encode(next_obs[:horizon])
    mse = prediction_error(torch.stack(predicted), targets)  # (H, B)
    return (rho_weights(rho, horizon, obs)[:, None] * mse).sum(0)


def fisher_diagonal(world_model: nn.Module, batches: Iterable[SequenceBatch], horizon: int | None = None,
                    rho: float = 0.5) -> ParamDict:
    """Diagonal empirical Fisher of the consistency loss, from per-batch gradients.

    ``F_i = mean over batches of (d L_batch / d theta_i)^2`` with ``L_batch`` the batch mean of
    :func:`consistency_loss`. This is the *batch* empirical Fisher (one squared gradient per minibatch,
    as in most EWC code), not the per-sample one: per-sample gradients of the 0.5M-parameter dynamics
    would cost B times the memory. It is therefore smaller than the per-sample Fisher by roughly the
    batch size where the mean gradient vanishes; ``method.ewc.coef`` absorbs the scale. The consistency loss is
    a Gaussian negative log-likelihood with fixed variance up to a constant factor, so its gradients
    are those of the log-likelihood the Fisher is defined on.

    Batches drawn from the PER buffer lean towards high-TD-error sequences; they are used unweighted. A
    world model with a ``transition_loss`` of its own (PETS's ensemble NLL, the loss it is trained on) is
    measured on that instead, over every transition of each batch's sequences.

    Args:
        world_model: the model whose parameters the Fisher is about (left unchanged, no ``.grad`` written).
        batches: sequences from the task's data, each with ``obs``, ``actions`` and ``next_obs``.
        horizon: H of the consistency loss. Pass the agent's horizon for replay batches (:class:`Batch`), which
            hold H+1 steps; None uses every step of each batch's sequences.
        rho: temporal weight of the consistency loss.

    Returns:
        Non-negative tensors shaped like the trainable parameters, keyed by parameter name; exactly
        zero for a parameter the loss does not depend on.

    Raises:
        ValueError: no batch was given.
    """
    params = trainable_parameters(world_model)
    names, tensors = list(params), list(params.values())
    fisher = {name: torch.zeros_like(p) for name, p in params.items()}
    count = 0
    own = getattr(world_model, "transition_loss", None)
    for batch in batches:
        if own is not None:  # a world model with an objective of its own (PETS): every transition of the batch
            states = torch.cat((batch.obs[None], batch.next_obs[:-1]))
            loss = own(states, batch.actions, batch.next_obs)
        else:
            steps = batch.actions.shape[0] if horizon is None else horizon
            loss = consistency_loss(world_model, batch.obs, batch.actions, batch.next_obs, steps, rho).mean()
        # allow_unused: a parameter outside the loss's graph has gradient (and Fisher) zero.
        grads = torch.autograd.grad(loss, tensors, allow_unused=True)
        for name, g in zip(names, grads):
            if g is not None:
                fisher[name] += g.detach().pow(2)
        count += 1
    if count == 0:
        raise ValueError("fisher_diagonal needs at least one batch")
    return {name: f / count for name, f in fisher.items()}


def ewc_penalty(world_model: nn.Module, anchors: Sequence[ParamDict], fishers: Sequence[ParamDict]) -> torch.Tensor:
    """``sum_k sum_i F_{k,i} (theta_i - theta*_{k,i})^2`` over the given (anchor, Fisher) pairs.

    The pairs can be one per previous task (Kirkpatrick et al.'s original form, memory growing with the
    number of tasks) or a single pair; :class:`EWC` passes one pair, the Fisher accumulated over tasks
    with the latest anchor (see there). Parameters missing from a pair are not penalised. The factor
    1/2 and the coefficient are the caller's.

    Args:
        world_model: the current model; the result has a graph to its parameters.
        anchors: per pair, the parameter values theta* to stay close to, by name.
        fishers: per pair, the non-negative diagonal Fisher F, by name (same keys as its anchor).

    Returns:
        A scalar tensor: 0 exactly at the anchor, and 0 wherever the Fisher is 0.
    """
    if len(anchors) != len(fishers):
        raise ValueError(f"{len(anchors)} anchors but {len(fishers)} Fisher estimates")
    params = trainable_parameters(world_model)
    total = next(iter(params.values())).new_zeros(())
    for anchor, fisher in zip(anchors, fishers):
        for name, f in fisher.items():
            total = total + (f * (params[name] - anchor[name]).pow(2)).sum()
    return total


class EWC(ContinualMethod):
    """Continual TD-MPC whose world model is held near its previous solutions by an EWC penalty.

    Online form: one Fisher ``F = F_1 + ... + F_k`` accumulated over the finished tasks and one anchor,
    the world model task k ended with. Because every task starts from the previous task's world model
    and is itself penalised towards the earlier anchors, the latest anchor already sits in the region
    the old tasks allow; this is the recursive Laplace approximation of the posterior (Huszár 2018,
    Schwarz et al. 2018), and it keeps the carried state at two copies of the world model whatever the
    number of tasks. The issue asks for a Fisher "accumulated over tasks", which is this form.
    """

    name = "ewc"
    reads = ("ewc",)
    description = "continual TD-MPC with an EWC penalty (accumulated diagonal Fisher) on the world model"

    def __init__(self, cfg: Config, spec: EnvSpec, device: torch.device):
        super().__init__(cfg, spec, device)
        self.fisher: ParamDict | None = None
        self.anchor: ParamDict | None = None
        self.tasks_seen = 0  # tasks whose Fisher is in ``self.fisher``

    def penalty(self, world_model: nn.Module) -> torch.Tensor:
        """``method.ewc.coef / 2 * sum_i F_i (theta_i - theta*_i)^2`` for the current world model."""
        assert self.fisher is not None and self.anchor is not None
        return 0.5 * self.cfg.method.ewc.coef * ewc_penalty(world_model, [self.anchor], [self.fisher])

    def world_model_loss(self, task: TaskState) -> Callable[[], torch.Tensor] | None:
        if self.fisher is None or self.cfg.method.ewc.coef <= 0:
            return None
        return lambda: self.penalty(task.world_model)

    def end_task(self, task: TaskState) -> None:
        """Estimate this task's Fisher at the final world model, add it, and move the anchor there."""
        cfg = self.cfg
        batches = (task.buffer.sample(cfg.agent.batch_size, task.rng) for _ in range(cfg.method.ewc.fisher_batches))
        fisher = fisher_diagonal(task.world_model, batches, horizon=cfg.agent.tdmpc.horizon, rho=cfg.agent.tdmpc.rho)
        if self.fisher is not None:
            fisher = {name: f + self.fisher[name] for name, f in fisher.items()}
        self.fisher = fisher
        self.anchor = {name: p.detach().clone() for name, p in trainable_parameters(task.world_model).items()}
        self.tasks_seen += 1

    # ---- persistence: plain tensors, so checkpoints load with weights_only -----------------
    def carry_state(self) -> dict[str, Any]:
        if self.fisher is None or self.anchor is None:
            return {}
        return {"fisher": {k: v.detach().cpu().clone() for k, v in self.fisher.items()},
                "anchor": {k: v.detach().cpu().clone() for k, v in self.anchor.items()},
                "tasks": self.tasks_seen}

    def load_carry_state(self, state: dict[str, Any]) -> None:
        # Replace, never merge: the checkpoint is the whole truth, also for a run resumed from it.
        if not state:
            self.fisher, self.anchor, self.tasks_seen = None, None, 0
            return
        self.fisher = {k: v.to(self.device) for k, v in state["fisher"].items()}
        self.anchor = {k: v.to(self.device) for k, v in state["anchor"].items()}
        self.tasks_seen = int(state["tasks"])
