"""PETS: probabilistic ensembles with trajectory sampling (Chua et al. 2018), the second model-based
agent under drago's continual methods (DRAGO paper Appendix E, "DRAGO-PETS").

The pieces, each usable on its own:

* :class:`ProbabilisticEnsemble`: E bootstrapped Gaussian MLPs over (state, action) predicting the
  next-state delta (and the reward), batched as (E, B, ·) (Chua et al. 2018 §4).
* :func:`gaussian_nll`, :func:`soft_clamp_logvar`, :func:`logvar_bound_penalty`, :func:`bootstrap_indices`:
  the training objective as pure functions.
* :func:`propagate`: trajectory sampling, TS-1 or TS-inf (Chua et al. 2018 §5).
* :func:`plan` / :func:`cem`: model-predictive control with the cross-entropy method over action
  sequences (Chua et al. 2018 §5), categorical over one-hot actions for the grid, Gaussian for
  continuous actions, following the conventions of :mod:`drago.agent.planner`.
* :class:`PetsWorldModel` and :class:`RewardHead`: the ensemble behind the world-model surface that the
  continual methods and evaluations use on TD-MPC's ``WorldModel``, and an agent's own learned reward.
* :class:`PetsAgent`: the small surface the trainer and the methods call on TD-MPC's ``Agent`` (``act``,
  ``random_action``, ``update``, ``state_dict``, ``heads``), with the ensemble as ``world_model``.

Everything runs on the device of the ensemble's parameters (CPU by default).
"""

from __future__ import annotations

import contextlib
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from drago.agent.agent import random_action
from drago.agent.losses import LOG_EPS
from drago.agent.protocol import PETS_CAPABILITIES

__all__ = [
    "PROPAGATION_MODES",
    "BatchedLinear",
    "CemResult",
    "PetsAgent",
    "PetsConfig",
    "PetsPlanSettings",
    "PetsWorldModel",
    "ProbabilisticEnsemble",
    "RewardBonus",
    "RewardFn",
    "RewardHead",
    "Rollout",
    "bootstrap_indices",
    "cem",
    "ensemble_mean_next",
    "gaussian_nll",
    "logvar_bound_penalty",
    "make_optimizer",
    "plan",
    "propagate",
    "soft_clamp_logvar",
]

# TS-1 re-draws each particle's member at every step; TS-inf draws it once per trajectory (Chua et al. 2018 §5).
PROPAGATION_MODES = ("ts1", "tsinf")

# The task's reward r(s, a, s') on batches of rows: (R, obs), (R, act), (R, obs) -> (R,).
RewardFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
# Multiplies non-negative predicted rewards at predicted next states (DRAGO's reviewer count bonus),
# with the semantics of drago.agent.planner.RewardBonus.
RewardBonus = Callable[[torch.Tensor], torch.Tensor]

# Coefficient of the learned log-variance bounds in the loss (Chua et al. 2018 §4 and appendix).
LOGVAR_BOUND_COEF = 0.01
# Initial bounds: the log-variance starts free in [-10, 0.5].
INIT_MAX_LOGVAR = 0.5
INIT_MIN_LOGVAR = -10.0
# Input dimensions whose spread is below this are left unscaled (e.g. a constant feature).
MIN_INPUT_STD = 1e-6


# ----------------------------------------------------------------------------- the objective
def soft_clamp_logvar(raw: torch.Tensor, max_logvar: torch.Tensor, min_logvar: torch.Tensor) -> torch.Tensor:
    """Softly bound a raw log-variance to [min_logvar, max_logvar] (Chua et al. 2018 §4 and appendix).

    ``logvar = max - softplus(max - raw)`` then ``logvar = min + softplus(logvar - min)``: smooth, close
    to the identity well inside the bounds, and it lets the bounds themselves receive gradients, so the
    network cannot make the variance collapse or blow up on inputs far from the data.
    """
    logvar = max_logvar - F.softplus(max_logvar - raw)
    return min_logvar + F.softplus(logvar - min_logvar)


def gaussian_nll(mean: torch.Tensor, logvar: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Gaussian negative log-likelihood without its constants, per ensemble member (Chua et al. 2018 §4).

    ``mean over rows and output dims of (mean - target)^2 * exp(-logvar) + logvar``: twice the NLL minus
    log(2 pi), the loss of the PETS ensemble. Inputs of shape (..., B, D) give a result of shape (...):
    (E, B, D) gives one value per member, (B, D) a scalar. The bound term is separate,
    :func:`logvar_bound_penalty`.
    """
    per_dim = (mean - target).pow(2) * torch.exp(-logvar) + logvar
    return per_dim.mean(dim=(-2, -1))


def logvar_bound_penalty(max_logvar: torch.Tensor, min_logvar: torch.Tensor,
                         coef: float = LOGVAR_BOUND_COEF) -> torch.Tensor:
    """``coef * (sum max_logvar - sum min_logvar)``: pulls the learned bounds together, so they end just
    around the log-variances the data supports (Chua et al. 2018 §4 and appendix)."""
    return coef * (max_logvar.sum() - min_logvar.sum())


def bootstrap_indices(n: int, members: int, rng: np.random.Generator | torch.Generator | None = None,
                      device: torch.device | str | None = None) -> torch.Tensor:
    """(members, n) int64 row indices: each member's own n rows drawn with replacement from 0..n-1.

    The bootstrap gives every member a different data set, so their disagreement measures epistemic
    uncertainty (Chua et al. 2018 §4). ``rng`` is a numpy Generator (indices drawn on the host, then
    copied), a torch Generator (drawn where it lives, no host round trip) or None (torch's global RNG).
    """
    if n < 1 or members < 1:
        raise ValueError(f"need n >= 1 and members >= 1, got n={n}, members={members}")
    if isinstance(rng, np.random.Generator):
        return torch.as_tensor(rng.integers(0, n, size=(members, n)), dtype=torch.long, device=device)
    if rng is None:
        return torch.randint(0, n, (members, n), device=device)
    idx = torch.randint(0, n, (members, n), generator=rng, device=rng.device)
    return idx if device is None else idx.to(device)


# ----------------------------------------------------------------------------- input statistics
@torch.no_grad()
def _merge_input_stats(module: nn.Module, x: torch.Tensor) -> None:
    """Merge rows (N, in) into a module's buffers ``input_mean``, ``input_var``, ``input_count`` (exact
    pooled mean and variance)."""
    x = x.to(module.input_mean.dtype)
    n = x.new_tensor(float(x.shape[0]))
    batch_mean = x.mean(0)
    batch_var = x.var(0, unbiased=False)
    total = module.input_count + n
    delta = batch_mean - module.input_mean
    mean = module.input_mean + delta * (n / total)
    m2 = module.input_var * module.input_count + batch_var * n + delta.pow(2) * (module.input_count * n / total)
    module.input_mean.copy_(mean)
    module.input_var.copy_(m2 / total)
    module.input_count.copy_(total)


def _input_std(module: nn.Module) -> torch.Tensor:
    std = module.input_var.sqrt()
    return torch.where(std < MIN_INPUT_STD, torch.ones_like(std), std)


# ----------------------------------------------------------------------------- the ensemble
class BatchedLinear(nn.Module):
    """``members`` independent linear layers as one batched matmul (weights (E, in, out), bias (E, 1, out)).

    Weights are drawn from a normal truncated at two standard deviations, std 1/(2 sqrt(in)), and biases
    start at zero, as in the PETS ensemble of Chua et al. 2018.
    """

    def __init__(self, members: int, in_dim: int, out_dim: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(members, in_dim, out_dim))
        self.bias = nn.Parameter(torch.zeros(members, 1, out_dim))
        std = 1.0 / (2.0 * math.sqrt(in_dim))
        nn.init.trunc_normal_(self.weight, std=std, a=-2 * std, b=2 * std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(E, rows, in) -> (E, rows, out)."""
        return torch.baddbmm(self.bias, x, self.weight)


class ProbabilisticEnsemble(nn.Module):
    """E probabilistic networks f_e(s, a) -> N(mu_e, diag(exp(logvar_e))) trained jointly (Chua et al. 2018 §4).

    The output is the next-state delta s' - s, followed by the reward when ``predict_reward``. Inputs
    (s, a) are standardised with statistics of the training rows (buffers ``input_mean``, ``input_var``,
    ``input_count``, saved in the state dict); outputs are not. The log-variance is softly bounded by the
    learned parameters ``max_logvar`` and ``min_logvar`` (one per output dim, shared by the members).

    Args:
        obs_dim, action_dim: sizes of s and a.
        members: the ensemble size E.
        hidden: width of every hidden layer.
        layers: number of hidden layers (SiLU, i.e. swish, activations).
        predict_reward: add the reward as a last output dimension.
    """

    def __init__(self, obs_dim: int, action_dim: int, members: int = 5, hidden: int = 200, layers: int = 4,
                 predict_reward: bool = True):
        super().__init__()
        if members < 1 or layers < 1:
            raise ValueError(f"need members >= 1 and layers >= 1, got {members}, {layers}")
        self.obs_dim = obs_dim
        self.action_dim = action_dim
        self.members = members
        self.predict_reward = predict_reward
        self.in_dim = obs_dim + action_dim
        self.out_dim = obs_dim + int(predict_reward)
        dims = [self.in_dim] + [hidden] * layers
        self.hidden = nn.ModuleList(BatchedLinear(members, a, b) for a, b in itertools.pairwise(dims))
        self.head = BatchedLinear(members, hidden, 2 * self.out_dim)
        self.max_logvar = nn.Parameter(torch.full((1, self.out_dim), INIT_MAX_LOGVAR))
        self.min_logvar = nn.Parameter(torch.full((1, self.out_dim), INIT_MIN_LOGVAR))
        self.register_buffer("input_mean", torch.zeros(self.in_dim))
        self.register_buffer("input_var", torch.ones(self.in_dim))
        self.register_buffer("input_count", torch.zeros(()))

    # ------------------------------------------------------------ input statistics
    @torch.no_grad()
    def update_input_stats(self, obs: torch.Tensor, action: torch.Tensor) -> None:
        """Merge these rows into the running input statistics (exact pooled mean and variance).

        Called on every training batch, the statistics converge to those of the data the model is
        trained on; a model that is not trained any more (a frozen copy) keeps its own.
        """
        _merge_input_stats(self, torch.cat((obs, action), dim=-1).reshape(-1, self.in_dim))

    @torch.no_grad()
    def fit_input_stats(self, obs: torch.Tensor, action: torch.Tensor) -> None:
        """Set the input statistics to exactly those of these rows (forgetting earlier ones)."""
        self.input_count.zero_()
        self.input_mean.zero_()
        self.input_var.fill_(1.0)
        self.update_input_stats(obs, action)

    def input_std(self) -> torch.Tensor:
        return _input_std(self)

    # ------------------------------------------------------------ prediction
    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, logvar), each (E, B, out_dim), of [s' - s, r] for inputs (B, ·) given to every member
        or (E, B, ·) with each member's own rows."""
        x = torch.cat((obs, action), dim=-1)
        x = (x - self.input_mean) / self.input_std()
        if x.dim() == 2:
            x = x.unsqueeze(0).expand(self.members, -1, -1)
        elif x.dim() != 3 or x.shape[0] != self.members:
            raise ValueError(f"inputs must be (B, n) or ({self.members}, B, n), got {tuple(x.shape)}")
        for layer in self.hidden:
            x = F.silu(layer(x))
        mean, raw_logvar = self.head(x).split(self.out_dim, dim=-1)
        return mean, soft_clamp_logvar(raw_logvar, self.max_logvar, self.min_logvar)

    # ------------------------------------------------------------ training
    def targets(self, obs: torch.Tensor, next_obs: torch.Tensor, reward: torch.Tensor | None) -> torch.Tensor:
        """[s' - s, r] (or s' - s alone without a reward output), the rows' regression targets."""
        delta = next_obs - obs
        if not self.predict_reward:
            return delta
        if reward is None:
            raise ValueError("this ensemble predicts the reward: the batch needs rewards")
        return torch.cat((delta, reward.reshape(*delta.shape[:-1], 1).to(delta.dtype)), dim=-1)

    def loss(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor, reward: torch.Tensor | None,
             indices: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(loss, metrics) on rows (B, ·): member e sees the rows ``indices[e]`` (all rows when None).

        loss = sum over members of :func:`gaussian_nll` + :func:`logvar_bound_penalty`. Summing (not
        averaging) over members keeps each member's gradient that of its own loss, whatever E is.
        Metrics are detached tensors: ``nll`` (mean over members), ``mse`` of the predicted mean,
        ``logvar`` (mean predicted log-variance).
        """
        target = self.targets(obs, next_obs, reward)
        if indices is not None:
            obs, action, target = obs[indices], action[indices], target[indices]
        mean, logvar = self(obs, action)
        if target.dim() == 2:
            target = target.unsqueeze(0).expand_as(mean)
        nll = gaussian_nll(mean, logvar, target)
        loss = nll.sum() + logvar_bound_penalty(self.max_logvar, self.min_logvar)
        with torch.no_grad():
            metrics = {"nll": nll.mean(), "mse": (mean - target).pow(2).mean(), "logvar": logvar.mean()}
        return loss, metrics

    def train_step(self, optimizer: torch.optim.Optimizer, batch_obs: torch.Tensor, batch_act: torch.Tensor,
                   batch_next_obs: torch.Tensor, batch_reward: torch.Tensor | None,
                   rng: np.random.Generator | torch.Generator | None = None,
                   extra_loss: Callable[[], torch.Tensor] | None = None,
                   update_stats: bool = True) -> dict[str, torch.Tensor]:
        """One gradient step on rows (B, ·), each member on its own bootstrap draw of them; metrics as
        detached tensors (no host sync).

        Args:
            extra_loss: a scalar added to this step's objective (a continual method's penalty on the
                world model: EWC, replayed or rehearsed transitions).
            update_stats: merge the batch into the input statistics first (:meth:`update_input_stats`).
        """
        if update_stats:
            self.update_input_stats(batch_obs, batch_act)
        indices = bootstrap_indices(batch_obs.shape[0], self.members, rng, device=batch_obs.device)
        loss, metrics = self.loss(batch_obs, batch_act, batch_next_obs, batch_reward, indices)
        if extra_loss is not None:
            extra = extra_loss()
            loss = loss + extra
            metrics["extra_loss"] = extra.detach()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        metrics["loss"] = loss.detach()
        return metrics

    def update(self, batch_obs: torch.Tensor, batch_act: torch.Tensor, batch_next_obs: torch.Tensor,
               batch_reward: torch.Tensor | None, rng: np.random.Generator | torch.Generator | None = None,
               *, optimizer: torch.optim.Optimizer, **kwargs: Any) -> dict[str, float]:
        """:meth:`train_step`, its metrics read back as floats with one host sync."""
        metrics = self.train_step(optimizer, batch_obs, batch_act, batch_next_obs, batch_reward, rng, **kwargs)
        values = torch.stack(list(metrics.values())).tolist()
        return dict(zip(metrics, values))


def make_optimizer(model: ProbabilisticEnsemble, lr: float = 1e-3, weight_decay: float = 0.0) -> torch.optim.Adam:
    """Adam over the whole ensemble; ``weight_decay`` (L2) applies to the weight matrices only, not to
    biases or the log-variance bounds (Chua et al. 2018 regularise the weights of their ensemble)."""
    weights = [layer.weight for layer in (*model.hidden, model.head)]
    ids = {id(p) for p in weights}
    others = [p for p in model.parameters() if id(p) not in ids]
    return torch.optim.Adam([{"params": weights, "weight_decay": weight_decay},
                             {"params": others, "weight_decay": 0.0}], lr=lr)


# ----------------------------------------------------------------------------- the world-model surface
def ensemble_mean_next(ensemble: ProbabilisticEnsemble, obs: torch.Tensor, action: torch.Tensor,
                       state_bounds: tuple[float, float] | None = None) -> torch.Tensor:
    """The ensemble's mean next state s + mean_e mu_e(s, a)[:obs] for rows (N, ·), clamped to ``state_bounds``."""
    mean, _ = ensemble(obs, action)
    following = obs + mean[..., :ensemble.obs_dim].mean(0)
    return following if state_bounds is None else following.clamp(*state_bounds)


class PetsWorldModel(nn.Module):
    """The ensemble behind the surface every continual method and evaluation uses on TD-MPC's ``WorldModel``.

    ``encode`` is the identity; ``forward(z, a)`` is the ensemble's mean prediction of the next state, clamped
    to the grid's [-1, 1] as the planner's particles are: what coverage, held-out retention, zero-shot
    planning and DRAGO's intrinsic reward read (docs: Methods, PETS). ``raw_next`` gives each member's mean
    prediction before the clamp, so rehearsal pulls every member towards its frozen old self rather than
    only their average; ``transition_loss`` is the ensemble's own objective on rows, for methods that add
    old transitions (replay) or measure the loss's curvature (EWC's Fisher).

    The ensemble predicts next states only (``predict_reward=False``): rewards belong to each agent's
    :class:`RewardHead`, which is what lets the ensemble be carried from task to task and shared by DRAGO's
    learner and reviewer.
    """

    def __init__(self, ensemble: ProbabilisticEnsemble, state_bounds: tuple[float, float] | None = None):
        super().__init__()
        self.ensemble = ensemble
        self.obs_dim = ensemble.obs_dim
        self.action_dim = ensemble.action_dim
        self.members = ensemble.members
        self.state_bounds = state_bounds

    def encode(self, obs: torch.Tensor) -> torch.Tensor:
        return obs

    def raw_next(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """(E, ..., obs): each member's mean next state, unclamped, for inputs of any leading shape (..., ·)."""
        lead = z.shape[:-1]
        flat = z.reshape(-1, self.obs_dim)
        mean, _ = self.ensemble(flat, action.reshape(-1, self.action_dim))
        return (flat + mean[..., :self.obs_dim]).reshape(self.members, *lead, self.obs_dim)

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The mean prediction over members of the next state, clamped to the state bounds (shape of ``z``)."""
        following = self.raw_next(z, action).mean(0)
        return following if self.state_bounds is None else following.clamp(*self.state_bounds)

    def transition_loss(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """Sum over members of :func:`gaussian_nll` of the next-state deltas of rows (..., ·), every member on
        every row: the ensemble's training objective without the bootstrap and the bound penalty."""
        obs = obs.reshape(-1, self.obs_dim)
        mean, logvar = self.ensemble(obs, action.reshape(-1, self.action_dim))
        target = (next_obs.reshape(-1, self.obs_dim) - obs).expand(self.members, -1, -1)
        return gaussian_nll(mean[..., :self.obs_dim], logvar[..., :self.obs_dim], target).sum()


class RewardHead(nn.Module):
    """One agent's learned reward r(s, a, s') for planning: an MLP (SiLU) over standardised inputs, trained by
    squared error on that agent's rows; its last layer starts at zero, so a fresh head predicts 0 everywhere.

    It is kept apart from the ensemble for the reason TD-MPC keeps its reward head apart from the world model
    (docs: Design, principles): the ensemble is carried from task to task and shared by DRAGO's learner and
    reviewer, whose rewards differ (the task's; the intrinsic one). The next state is an input because
    the planner scores each particle's own sampled transition.
    """

    def __init__(self, obs_dim: int, action_dim: int, hidden: int = 200, layers: int = 2):
        super().__init__()
        self.in_dim = 2 * obs_dim + action_dim
        modules: list[nn.Module] = []
        for a, b in itertools.pairwise([self.in_dim] + [hidden] * layers):
            modules += [nn.Linear(a, b), nn.SiLU()]
        last = nn.Linear(hidden, 1)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.net = nn.Sequential(*modules, last)
        self.register_buffer("input_mean", torch.zeros(self.in_dim))
        self.register_buffer("input_var", torch.ones(self.in_dim))
        self.register_buffer("input_count", torch.zeros(()))

    def forward(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """(...,) rewards of rows (..., ·)."""
        x = torch.cat((obs, action, next_obs), dim=-1)
        return self.net((x - self.input_mean) / _input_std(self)).squeeze(-1)

    def train_step(self, optimizer: torch.optim.Optimizer, obs: torch.Tensor, action: torch.Tensor,
                   next_obs: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        """One step of mean squared error on rows (N, ·), their inputs merged into the statistics first;
        the loss, detached."""
        _merge_input_stats(self, torch.cat((obs, action, next_obs), dim=-1))
        loss = (self(obs, action, next_obs) - reward.to(obs.dtype)).pow(2).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return loss.detach()


# ----------------------------------------------------------------------------- trajectory sampling
class Rollout(NamedTuple):
    """Particles of :func:`propagate`.

    Attributes:
        states: (H+1, N, P, obs) predicted states, states[0] the start.
        rewards: (H, N, P) reward of each step.
        members: (H, N, P) int64: the member that predicted each step of each particle.
    """

    states: torch.Tensor
    rewards: torch.Tensor
    members: torch.Tensor


def _assign_members(count: int, particles: int, members: int, device: torch.device,
                    generator: torch.Generator | None) -> torch.Tensor:
    """(count, particles) member of every particle: each row a random permutation of
    0, 1, .., E-1, 0, 1, ..: every member predicts P/E of a candidate's particles when E divides P."""
    order = torch.rand(count, particles, generator=generator, device=device).argsort(dim=1)
    return order % members


def _member_order(member: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(order, inverse): the permutation that sorts rows by their member, and its inverse."""
    order = torch.argsort(member, stable=True)
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(order.shape[0], device=order.device)
    return order, inverse


def _predict_assigned(model: nn.Module, obs: torch.Tensor, action: torch.Tensor, member: torch.Tensor,
                      balanced: bool, order: tuple[torch.Tensor, torch.Tensor] | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean, logvar), each (R, out), of rows (R, ·), row r predicted by member ``member[r]``.

    Balanced assignments (each member R/E rows) are sorted by member and run as (E, R/E, ·): every row
    costs one member's forward. Otherwise every member predicts every row and the row's own is kept.
    ``order`` is :func:`_member_order` of ``member`` when the caller already has it.
    """
    rows = obs.shape[0]
    if balanced:
        order, inverse = order if order is not None else _member_order(member)
        e = model.members
        mean, logvar = model(obs[order].view(e, rows // e, -1), action[order].view(e, rows // e, -1))
        return mean.reshape(rows, -1)[inverse], logvar.reshape(rows, -1)[inverse]
    mean, logvar = model(obs, action)
    pick = member.view(1, rows, 1).expand(1, rows, mean.shape[-1])
    return mean.gather(0, pick)[0], logvar.gather(0, pick)[0]


@torch.no_grad()
def propagate(model: nn.Module, obs: torch.Tensor, actions: torch.Tensor, particles: int, mode: str = "tsinf",
              generator: torch.Generator | None = None, known_reward: RewardFn | None = None,
              state_bounds: tuple[float, float] | None = None, bonus: RewardBonus | None = None) -> Rollout:
    """Trajectory sampling (Chua et al. 2018 §5): P particles per action sequence, each a sample path
    through the ensemble.

    At each step a particle is predicted by one member and its next state is a draw
    ``s + mean + exp(logvar / 2) * noise`` from that member's Gaussian (aleatoric uncertainty); which
    member predicts it carries the epistemic uncertainty:

    * ``"tsinf"`` (TS-inf, the default): a particle keeps one member for the whole horizon.
    * ``"ts1"`` (TS-1): every particle draws its member again at every step.

    TS-inf is the default: Chua et al. found the two comparable (§6), and TS-inf needs one member
    assignment (a random permutation of each candidate's particles) per call instead of one per step,
    and keeps each particle a consistent hypothesis about the dynamics. Assignments are balanced, each
    member predicting P/E of a candidate's particles, when E divides P (as in Chua et al.); every step
    is then one batched forward of R/E rows per member. Otherwise the assignment is as even as P
    allows and every member evaluates every row (E times the work).

    Args:
        model: a :class:`ProbabilisticEnsemble`, or any module with ``members``, ``obs_dim``,
            ``predict_reward`` and the same ``forward``.
        obs: (N, obs) start state of each of N action sequences (or (obs,) shared by all).
        actions: (H, N, act) the action sequences.
        particles: P.
        generator: the torch Generator of the draws, on the model's device (None: the global RNG).
        known_reward: the task's reward r(s, a, s') on predicted rows, used instead of the model's.
        state_bounds: clamp predicted states to [low, high] (the grid's observations lie in [-1, 1]).
        bonus: multiplies non-negative rewards by ``bonus(next state)`` (DRAGO's reviewer).

    Returns:
        A :class:`Rollout` with states (H+1, N, P, obs), rewards (H, N, P) and members (H, N, P).
    """
    if mode not in PROPAGATION_MODES:
        raise ValueError(f"unknown propagation mode '{mode}'; valid: {', '.join(PROPAGATION_MODES)}")
    if known_reward is None and not model.predict_reward:
        raise ValueError("the model predicts no reward: pass known_reward")
    horizon, count = actions.shape[:2]
    obs_dim, rows = model.obs_dim, count * particles
    state = obs.expand(count, -1) if obs.dim() == 1 else obs
    state = state.repeat_interleave(particles, dim=0)  # (N * P, obs), candidate-major
    balanced = particles % model.members == 0
    member = _assign_members(count, particles, model.members, state.device, generator).view(rows)
    # TS-inf sorts its rows by member once per call, not once per step.
    order = _member_order(member) if balanced else None
    action_rows = actions.repeat_interleave(particles, dim=1)  # (H, N * P, act), candidate-major
    states, rewards, used = [state], [], []
    for t in range(horizon):
        if mode == "ts1" and t > 0:
            member = _assign_members(count, particles, model.members, state.device, generator).view(rows)
            order = _member_order(member) if balanced else None
        action = action_rows[t]
        mean, logvar = _predict_assigned(model, state, action, member, balanced, order)
        noise = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
        sample = mean + torch.exp(0.5 * logvar) * noise
        next_state = state + sample[:, :obs_dim]
        if state_bounds is not None:
            next_state = next_state.clamp(*state_bounds)
        reward = known_reward(state, action, next_state) if known_reward is not None else sample[:, obs_dim]
        if bonus is not None:
            reward = torch.where(reward >= 0, reward * bonus(next_state), reward)
        states.append(next_state)
        rewards.append(reward)
        used.append(member)
        state = next_state
    return Rollout(torch.stack(states).view(horizon + 1, count, particles, obs_dim),
                   torch.stack(rewards).view(horizon, count, particles),
                   torch.stack(used).view(horizon, count, particles))


# ----------------------------------------------------------------------------- planning
@dataclass
class PetsPlanSettings:
    """CEM over action sequences on the ensemble (Chua et al. 2018 §5).

    Defaults are Chua et al.'s CEM settings for cartpole: population 400, 40 elites, 5 iterations,
    momentum 0.1, 20 particles, horizon 25, undiscounted return.
    """

    horizon: int = 25
    iterations: int = 5
    population: int = 400
    elites: int = 40
    particles: int = 20
    momentum: float = 0.1  # new = momentum * old + (1 - momentum) * elite statistics
    discount: float = 1.0
    init_std: float = 0.5  # continuous: a quarter of the [-1, 1] range
    min_std: float = 0.0  # continuous: floor of the CEM std
    propagation: str = "tsinf"
    # Training (not eval) draws the first action from the final CEM distribution instead of taking its
    # mode; Chua et al. execute the mode (explore=False).
    explore: bool = True

    def __post_init__(self) -> None:
        if not 1 <= self.elites <= self.population:
            raise ValueError(f"need 1 <= elites <= population, got {self.elites}, {self.population}")
        if self.horizon < 1 or self.iterations < 1 or self.particles < 1:
            raise ValueError("horizon, iterations and particles must be >= 1")
        if self.propagation not in PROPAGATION_MODES:
            raise ValueError(f"unknown propagation '{self.propagation}'; valid: {', '.join(PROPAGATION_MODES)}")


class CemResult(NamedTuple):
    """action: (n_a,) or (B, n_a); mean: the final CEM mean (H, n_a) or (H, B, n_a), one-hot
    probabilities on discrete actions, the warm start of the next continuous plan."""

    action: torch.Tensor
    mean: torch.Tensor


def _sequence_returns(model: nn.Module, obs: torch.Tensor, actions: torch.Tensor, s: PetsPlanSettings,
                      generator: torch.Generator | None, known_reward: RewardFn | None,
                      state_bounds: tuple[float, float] | None, bonus: RewardBonus | None) -> torch.Tensor:
    """(B, M) predicted return (mean over particles of sum_t discount^t r_t) of the (H, B, M, n_a) sequences
    from the B start states."""
    horizon, problems, count, n_a = actions.shape
    starts = obs.repeat_interleave(count, dim=0)
    out = propagate(model, starts, actions.reshape(horizon, problems * count, n_a), s.particles, s.propagation,
                    generator, known_reward, state_bounds, bonus)
    scale = s.discount ** torch.arange(horizon, device=obs.device, dtype=out.rewards.dtype)
    returns = (out.rewards * scale[:, None, None]).sum(0).mean(-1)
    # A diverged particle must not make its sequence an elite.
    returns = torch.nan_to_num(returns, nan=-torch.inf, posinf=-torch.inf)
    return returns.view(problems, count)


def _elite_sequences(actions: torch.Tensor, returns: torch.Tensor, k: int) -> torch.Tensor:
    """(H, B, k, n_a): each problem's k highest-return sequences."""
    idx = torch.topk(returns, k, dim=-1).indices
    problems = torch.arange(returns.shape[0], device=returns.device)[:, None]
    return actions[:, problems, idx]


@torch.no_grad()
def cem(model: nn.Module, obs: torch.Tensor, s: PetsPlanSettings, discrete: bool, eval_mode: bool = True,
        warm_mean: torch.Tensor | None = None, generator: torch.Generator | None = None,
        known_reward: RewardFn | None = None, state_bounds: tuple[float, float] | None = None,
        bonus: RewardBonus | None = None) -> CemResult:
    """Cross-entropy method over action sequences on the ensemble's predicted return (Chua et al. 2018 §5).

    ``obs`` is one observation (n,) or B independent ones (B, n), planned as one batch.

    * Discrete (one-hot actions, the grid): a categorical distribution per step, starting uniform; each
      iteration samples ``population`` one-hot sequences and moves the probabilities toward the elites'
      action frequencies. The action is the one-hot of the first step's most likely action, or in
      training with ``explore`` a draw from it: always exactly one 1.
    * Continuous: a Gaussian per step (mean 0 or the shifted previous plan, std ``init_std``), samples
      clipped to [-1, 1]; mean and variance move toward the elites'. The action is the first step's
      mean, or in training with ``explore`` a draw around it, clipped to [-1, 1].

    Elites are the unweighted top ``elites`` of each iteration, as in Chua et al.
    """
    single = obs.dim() == 1
    obs = obs[None] if single else obs
    problems, n_a = obs.shape[0], model.action_dim
    h, m = s.horizon, s.population
    args = (generator, known_reward, state_bounds, bonus)
    if discrete:
        mean = obs.new_full((h, problems, n_a), 1.0 / n_a)
        for _ in range(s.iterations):
            idx = torch.multinomial(mean.reshape(-1, n_a), m, replacement=True, generator=generator)
            actions = F.one_hot(idx, n_a).to(obs.dtype).view(h, problems, m, n_a)
            returns = _sequence_returns(model, obs, actions, s, *args)
            elites = _elite_sequences(actions, returns, s.elites)
            mean = s.momentum * mean + (1 - s.momentum) * elites.mean(2)
        first = mean[0]
        if s.explore and not eval_mode:
            choice = torch.multinomial(first, 1, generator=generator)[:, 0]
        else:
            choice = first.argmax(-1)
        action = F.one_hot(choice, n_a).to(obs.dtype)
    else:
        mean = obs.new_zeros((h, problems, n_a))
        if warm_mean is not None:
            warm = warm_mean[:, None] if single else warm_mean
            shift = min(h - 1, warm.shape[0] - 1)
            mean[:shift] = warm[1:shift + 1]
        var = obs.new_full((h, problems, n_a), s.init_std ** 2)
        for _ in range(s.iterations):
            noise = torch.randn((h, problems, m, n_a), generator=generator, device=obs.device, dtype=obs.dtype)
            actions = (mean[:, :, None] + var.sqrt()[:, :, None] * noise).clamp(-1, 1)
            returns = _sequence_returns(model, obs, actions, s, *args)
            elites = _elite_sequences(actions, returns, s.elites)
            mean = s.momentum * mean + (1 - s.momentum) * elites.mean(2)
            var = s.momentum * var + (1 - s.momentum) * elites.var(2, unbiased=False)
            var = var.clamp_min(s.min_std ** 2)
        action = mean[0]
        if s.explore and not eval_mode:
            noise = torch.randn(action.shape, generator=generator, device=obs.device, dtype=obs.dtype)
            action = action + var[0].sqrt() * noise
        action = action.clamp(-1, 1)
    return CemResult(action[0], mean[:, 0]) if single else CemResult(action, mean)


def plan(model: nn.Module, obs: torch.Tensor, s: PetsPlanSettings, discrete: bool, **kwargs: Any) -> torch.Tensor:
    """The action of :func:`cem` alone: (n_a,) for an observation (n,), (B, n_a) for (B, n)."""
    return cem(model, obs, s, discrete, **kwargs).action


# ----------------------------------------------------------------------------- the agent
@dataclass
class PetsConfig:
    """A PETS agent: the ensemble, its optimizer and the planner (Chua et al. 2018 §4-5)."""

    members: int = 5
    hidden: int = 200
    layers: int = 4
    lr: float = 1e-3
    weight_decay: float = 0.0  # L2 on the weights; Chua et al. use small per-layer values
    predict_reward: bool = True
    plan: PetsPlanSettings = field(default_factory=PetsPlanSettings)
    random_action_probs: tuple[float, ...] = (0.2, 0.2, 0.6)  # grid seed phase (left, right, forward)

    def build_world_model(self, obs_dim: int, action_dim: int,
                          device: torch.device | str = "cpu") -> ProbabilisticEnsemble:
        return ProbabilisticEnsemble(obs_dim, action_dim, self.members, self.hidden, self.layers,
                                     self.predict_reward).to(device)


class PetsAgent:
    """PETS as a :class:`~drago.agent.protocol.ContinualAgent`, the protocol TD-MPC's ``Agent`` implements too.

    Rewards, three ways:

    * ``reward_head`` (what drago's trainer builds, ``agent.pets.reward=learned``): the agent learns
      r(s, a, s') with a :class:`RewardHead` of its own, over a :class:`PetsWorldModel` that predicts states
      only, and plans on the head's reward of each particle's transition. This is what the DRAGO paper's
      Appendix E implies: DRAGO-PETS runs the MiniGrid tasks with dense reward because the authors could not
      make PETS work with sparse reward, the failure of a reward the agent has to learn from its data (a
      sparse reward is almost always 0, so a learned reward and the predicted returns are flat), and
      DRAGO's tasks, its reviewer's reward included, reach the agent only through rewards in the data, as
      for TD-MPC's reward head.
    * ``known_reward=r(s, a, s')`` evaluated on the predicted rows (``agent.pets.reward=known``): Chua et
      al.'s own setting, where each task's cost function is given.
    * neither: the ensemble learns the reward with the dynamics (``predict_reward``), the standalone form.

    Differences from TD-MPC's ``Agent``:

    * no latent space: the ensemble predicts next observations (through deltas) directly;
    * no policy or value heads: no value bootstrap, the planner's return is the predicted H-step return
      alone, so methods that need a TD target (curiosity) cannot run on it;
    * the planner has no policy prior, no horizon or std schedule (``step`` is unused), and its
      stochasticity comes from the ensemble and the CEM samples;
    * ``update`` returns a uniform ``priority``: PETS samples its data uniformly;
    * ``state_dict`` holds the planner's warm start and the reward head with its optimizer: the world model
      and its optimizer are passed in and saved by whoever owns them, as for TD-MPC's ``Agent``.

    Args:
        world_model: the ensemble, or a :class:`PetsWorldModel` around one; a continual method may share,
            copy or freeze it.
        world_optimizer: its optimizer (None: :func:`make_optimizer` with ``cfg.lr``, ``cfg.weight_decay``).
        cfg: agent settings.
        discrete: one-hot actions (grid; predicted states then clamped to [-1, 1]) or continuous in [-1, 1].
        known_reward: the task's reward r(s, a, s') on predicted rows instead of a learned one.
        generator: torch Generator of the planner's and the bootstrap's draws, on the world model's device
            (None: the global RNG, which drago's trainer saves with every resumable checkpoint).
        reward_head: the agent's own learned reward (exclusive with ``known_reward``).
    """

    capabilities = PETS_CAPABILITIES

    def __init__(self, world_model: ProbabilisticEnsemble | PetsWorldModel,
                 world_optimizer: torch.optim.Optimizer | None = None, cfg: PetsConfig | None = None,
                 discrete: bool = True, known_reward: RewardFn | None = None,
                 generator: torch.Generator | None = None, reward_head: RewardHead | None = None):
        self.cfg = cfg or PetsConfig()
        self.world_model = world_model
        self.ensemble: ProbabilisticEnsemble = getattr(world_model, "ensemble", world_model)
        self.world_optimizer = world_optimizer or make_optimizer(self.ensemble, self.cfg.lr, self.cfg.weight_decay)
        self.discrete = discrete
        self.generator = generator
        self.device = next(self.ensemble.parameters()).device
        self.state_bounds = (-1.0, 1.0) if discrete else None
        self._warm_mean: torch.Tensor | None = None
        if reward_head is not None and known_reward is not None:
            raise ValueError("give a learned reward_head or a known_reward, not both")
        self.reward_head = reward_head
        self.reward_optimizer = (torch.optim.Adam(reward_head.parameters(), lr=self.cfg.lr)
                                 if reward_head is not None else None)
        self.known_reward = known_reward
        self._plan_reward: RewardFn | None = known_reward if reward_head is None else reward_head
        if self._plan_reward is None and not self.ensemble.predict_reward:
            raise ValueError("an ensemble without a reward output needs known_reward or a reward_head")

    def autocast(self):
        """PETS runs in float32: nothing to enter (the TD-MPC agent's reduced-precision context)."""
        return contextlib.nullcontext()

    # ------------------------------------------------------------------ acting
    @torch.no_grad()
    def act(self, obs: np.ndarray, step: int, eval_mode: bool, first_step: bool,
            bonus: RewardBonus | None = None) -> np.ndarray:
        """Plan one action for an observation (n,), or one for each of B observations (B, n) planned as a
        batch (numpy in, numpy out). ``step`` is unused (PETS has no schedules)."""
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        warm = None if first_step or self.discrete else self._warm_mean
        # A plan for another number of problems (an evaluation's batch between learner steps) cannot warm this one.
        if warm is not None and (warm.dim() != obs_t.dim() + 1 or (obs_t.dim() == 2 and warm.shape[1] != obs_t.shape[0])):
            warm = None
        result = cem(self.ensemble, obs_t, self.cfg.plan, self.discrete, eval_mode=eval_mode, warm_mean=warm,
                     generator=self.generator, known_reward=self._plan_reward, state_bounds=self.state_bounds,
                     bonus=bonus)
        if not self.discrete:
            self._warm_mean = result.mean
        return result.action.cpu().numpy()

    def random_action(self, rng: np.random.Generator) -> np.ndarray:
        return random_action(rng, self.ensemble.action_dim, self.discrete, self.cfg.random_action_probs)

    # ---------------------------------------------------------------- learning
    @staticmethod
    def transitions(batch: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(obs, action, next_obs, reward) rows of a replay ``Batch`` of (H+1)-long sequences: all its
        (H+1) * B transitions, s_t = s_0 for t = 0 and next_obs[t-1] after."""
        states = torch.cat((batch.obs[None], batch.next_obs[:-1]), dim=0)
        obs_dim, act_dim = states.shape[-1], batch.actions.shape[-1]
        return (states.reshape(-1, obs_dim), batch.actions.reshape(-1, act_dim),
                batch.next_obs.reshape(-1, obs_dim), batch.rewards.reshape(-1))

    @torch.no_grad()
    def prediction_score(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """Mean over rows of -log(mean_dims (mean prediction - s')^2): the one-step form of TD-MPC's prediction
        score, the quantity DRAGO's intrinsic reward compares with its threshold (paper §3.2)."""
        predicted = ensemble_mean_next(self.ensemble, obs, action, self.state_bounds)
        return -torch.log((predicted - next_obs).pow(2).mean(-1) + LOG_EPS).mean()

    def update(self, batch: Any, step: int = 0, train_world_model: bool = True,
               world_model_loss: Callable[[], torch.Tensor] | None = None,
               policy_rows: int | None = None) -> dict[str, torch.Tensor]:
        """One bootstrapped gradient step of the ensemble (when ``train_world_model``) and one of the reward
        head on a replay ``Batch``; metrics as tensors (no host sync), with a uniform ``priority`` for the
        first ``policy_rows`` sequences (all without it)."""
        rows = batch.obs.shape[0] if policy_rows is None else policy_rows
        priority = batch.obs.new_ones(rows)
        metrics: dict[str, torch.Tensor] = {}
        if train_world_model or self.reward_head is not None:
            obs, action, next_obs, reward = self.transitions(batch)
        if train_world_model:
            score = self.prediction_score(obs, action, next_obs)
            model = self.ensemble.train_step(self.world_optimizer, obs, action, next_obs,
                                             reward if self.ensemble.predict_reward else None, self.generator,
                                             extra_loss=world_model_loss)
            metrics = {f"model_{k}": v for k, v in model.items()}
            metrics["mean_prediction_score"] = score
        if self.reward_head is not None:
            metrics["reward_loss"] = self.reward_head.train_step(self.reward_optimizer, obs, action, next_obs, reward)
        metrics["priority"] = priority
        return metrics

    # ------------------------------------------------------------- persistence
    def task_state(self) -> dict[str, Any]:
        """The learned reward head (nothing when the learner is told the reward): a task checkpoint's learner."""
        return {"learner": {} if self.reward_head is None else self.reward_head.state_dict()}

    def load_task_state(self, state: dict[str, Any]) -> None:
        if self.reward_head is not None:
            self.reward_head.load_state_dict(state["learner"])

    def trained_modules(self) -> dict[str, nn.Module]:
        return {} if self.reward_head is None else {"learner reward head": self.reward_head}

    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {"warm_mean": None if self._warm_mean is None else self._warm_mean.clone()}
        if self.reward_head is not None:
            state["reward_head"] = self.reward_head.state_dict()
            state["reward_optimizer"] = self.reward_optimizer.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        warm = state.get("warm_mean")
        self._warm_mean = None if warm is None else warm.to(self.device)
        if self.reward_head is not None:
            self.reward_head.load_state_dict(state["reward_head"])
            self.reward_optimizer.load_state_dict(state["reward_optimizer"])
