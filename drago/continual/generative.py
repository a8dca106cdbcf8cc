"""DRAGO's building blocks as modules and pure functions (paper §3.1; docs: Design, paper and code).

* :class:`VAE` over (latent observation, action) and its loss;
* :func:`rehearsal_loss`: distillation of the frozen previous world model on generated pairs;
* :func:`intrinsic_reward`: the reviewer's reward, in the official code's form or the paper's;
* :class:`GridCounts` and :class:`ContinuousCounts`: the count bonus of reviewer planning on the grid
  and on continuous states.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn

from drago.agent.losses import LOG_EPS, prediction_error
from drago.agent.networks import WorldModel
from drago.config import INTRINSIC_REWARDS


class VAE(nn.Module):
    """Gaussian VAE: Linear-ELU-Linear-ELU-Linear encoder to (mu, log var), mirrored decoder.

    PyTorch's default initialisation, as in the official code (only the agent is orthogonally
    initialised). The decoder output is linear: generated grid actions are continuous vectors.
    """

    def __init__(self, input_dim: int, hidden_dim: int, latent_dim: int):
        super().__init__()
        self.input_dim = input_dim
        self.latent_dim = latent_dim
        self.encoder = nn.Sequential(nn.Linear(input_dim, hidden_dim), nn.ELU(), nn.Linear(hidden_dim, hidden_dim),
                                     nn.ELU(), nn.Linear(hidden_dim, 2 * latent_dim))
        self.decoder = nn.Sequential(nn.Linear(latent_dim, hidden_dim), nn.ELU(), nn.Linear(hidden_dim, hidden_dim),
                                     nn.ELU(), nn.Linear(hidden_dim, input_dim))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        mu, log_var = self.encoder(x).chunk(2, dim=-1)
        u = mu + torch.exp(0.5 * log_var) * torch.randn_like(mu)
        return self.decoder(u), mu, log_var

    @torch.no_grad()
    def sample(self, n: int) -> torch.Tensor:
        """Decoder means at u ~ N(0, I): no output noise (paper §3.1)."""
        device = self.decoder[0].weight.device
        return self.decoder(torch.randn(n, self.latent_dim, device=device))


def vae_loss(reconstruction: torch.Tensor, x: torch.Tensor, mu: torch.Tensor, log_var: torch.Tensor,
             recon_coef: float, kl_coef: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(total, reconstruction, KL); both terms are means over batch and dimensions (paper §3.1)."""
    recon = (reconstruction - x).pow(2).mean()
    kl = -0.5 * (1 + log_var - mu.pow(2) - log_var.exp()).mean()
    return recon_coef * recon + kl_coef * kl, recon, kl


def rehearsal_loss(world_model: WorldModel, old_world_model: WorldModel, states: torch.Tensor,
                   actions: torch.Tensor, target: str = "pre_squash") -> torch.Tensor:
    """Mean squared distance between the current and the frozen old dynamics on generated inputs.

    Args:
        target: ``pre_squash`` compares raw MLP outputs, before the clamp and tanh (the official code);
            ``post_squash`` compares next-state predictions as the planner sees them.
    """
    if target == "pre_squash":
        with torch.no_grad():
            goal = old_world_model.raw_next(states, actions)
        return (world_model.raw_next(states, actions) - goal).pow(2).mean()
    with torch.no_grad():
        goal = old_world_model(states, actions)
    return (world_model(states, actions) - goal).pow(2).mean()


@dataclass
class IntrinsicReward:
    reward: torch.Tensor  # r_old - alpha * cost
    old_reward: torch.Tensor  # how well the old model predicts the transition, in (0, 1)
    cost: torch.Tensor  # how well the current model predicts it, in (0, 1)


@torch.no_grad()
def intrinsic_reward(old_world_model: WorldModel, world_model: WorldModel, obs: torch.Tensor,
                     actions: torch.Tensor, next_obs: torch.Tensor, threshold: float, cost_coef: float,
                     variant: str = "code") -> IntrinsicReward:
    """The reviewer's reward for transitions (s, a, s'): high where the old model is right and the
    current one is wrong (paper §3.2). Any leading batch shape.

    Args:
        threshold: theta, the previous task's prediction-score EMA (``code`` variant only).
        variant: ``code`` = sigmoid(4(-log MSE_old - theta)) - alpha*sigmoid(-log MSE_cur - theta), range
            (-alpha, 1); ``paper`` = sigmoid(-log|err_old|) - alpha*sigmoid(-log|err_cur|) with the mean
            absolute error and no offset.
    """
    z, target = old_world_model.encode(obs), old_world_model.encode(next_obs)
    old_pred, cur_pred = old_world_model(z, actions), world_model(z, actions)
    if variant == "code":
        old_score = -torch.log(prediction_error(old_pred, target) + LOG_EPS)
        cur_score = -torch.log(prediction_error(cur_pred, target) + LOG_EPS)
        old_reward = torch.sigmoid(4.0 * (old_score - threshold))
        cost = torch.sigmoid(cur_score - threshold)
    elif variant == "paper":
        old_reward = torch.sigmoid(-torch.log((old_pred - target).abs().mean(-1) + LOG_EPS))
        cost = torch.sigmoid(-torch.log((cur_pred - target).abs().mean(-1) + LOG_EPS))
    else:
        raise ValueError(f"unknown intrinsic reward variant '{variant}'; valid: {', '.join(INTRINSIC_REWARDS)}")
    return IntrinsicReward(old_reward - cost_coef * cost, old_reward, cost)


class GridCounts:
    """Visit counts over the 27 x 27 x 4 grid states; bonus 1/sqrt(N + 0.99999) - 1/99999 (docs: Design, paper and code).

    Observations are mapped to cells by rounding: the official code truncates, which files even exact
    observations of x, y in {2, 3, 6, 9} one cell too low (docs: Design, departures from the official code).
    """

    SIZE = 27

    def __init__(self, device: torch.device | str = "cpu"):
        self.table = torch.zeros(self.SIZE, self.SIZE, 4, device=device)

    def index(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = torch.round((obs[..., 0] + 1) * self.SIZE / 2).long().clamp(0, self.SIZE - 1)
        y = torch.round((obs[..., 1] + 1) * self.SIZE / 2).long().clamp(0, self.SIZE - 1)
        d = torch.round((obs[..., 2] + 1) * 2).long().clamp(0, 3)
        return x, y, d

    def update(self, obs: torch.Tensor) -> None:
        self.table.index_put_(self.index(obs.reshape(-1, 3)), torch.ones(obs.reshape(-1, 3).shape[0],
                              device=self.table.device), accumulate=True)

    def bonus(self, obs: torch.Tensor) -> torch.Tensor:
        return 1.0 / torch.sqrt(self.table[self.index(obs)] + 0.99999) - 1.0 / 99999

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"table": self.table.cpu().clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.table.copy_(state["table"])


class ContinuousCounts:
    """Classifier pseudo-counts over continuous states for reviewer planning (docs: Design, paper and code, DMC), bounded.

    As in the official code's ``ContPseudoCounts``: a one-hidden-layer classifier learns, one Adam step
    per visited state, to tell visited states (label 1) from N(0, I) samples (label 0), and the state's
    pseudo-count comes from the change in its probability across that step,
    N = max(0, (1 - p_prev) / (p - p_prev + 1e-8)), both probabilities clipped to [1e-6, 1 - 1e-6].

    The official bonus 1/sqrt(N + 1e-8) reaches 10^4 wherever the last step lowered p (N = 0), which
    swamps every reward in planning. Here the bonus is 1/sqrt(N + 1), always in (0, 1] like the grid's:
    1 where the step lowered p, near 0 where it left p unchanged (a huge pseudo-count), and in between
    where it raised p, less the more often the state has been visited.
    """

    HIDDEN = 128
    LR = 1e-3
    CLIP = 1e-6

    def __init__(self, obs_dim: int, device: torch.device | str = "cpu"):
        self.classifier = nn.Sequential(nn.Linear(obs_dim, self.HIDDEN), nn.ReLU(), nn.Linear(self.HIDDEN, 1)).to(device)
        self.previous = copy.deepcopy(self.classifier).requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.classifier.parameters(), lr=self.LR)

    def update(self, obs: torch.Tensor) -> None:
        """One classifier step on one visited state (or a batch of them) against as many N(0, I) draws."""
        visited = obs.reshape(-1, obs.shape[-1])
        self.previous.load_state_dict(self.classifier.state_dict())
        inputs = torch.cat((visited, torch.randn_like(visited)))
        labels = torch.cat((torch.ones(len(visited), 1, device=obs.device), torch.zeros(len(visited), 1, device=obs.device)))
        loss = nn.functional.binary_cross_entropy_with_logits(self.classifier(inputs), labels)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()

    @torch.no_grad()
    def count(self, obs: torch.Tensor) -> torch.Tensor:
        p = torch.sigmoid(self.classifier(obs)).squeeze(-1).clamp(self.CLIP, 1 - self.CLIP)
        p_prev = torch.sigmoid(self.previous(obs)).squeeze(-1).clamp(self.CLIP, 1 - self.CLIP)
        return ((1 - p_prev) / (p - p_prev + 1e-8)).clamp(min=0)

    @torch.no_grad()
    def bonus(self, obs: torch.Tensor) -> torch.Tensor:
        return 1.0 / torch.sqrt(self.count(obs) + 1.0)

    def state_dict(self) -> dict:
        return {"classifier": self.classifier.state_dict(), "previous": self.previous.state_dict(),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.classifier.load_state_dict(state["classifier"])
        self.previous.load_state_dict(state["previous"])
        self.optimizer.load_state_dict(state["optimizer"])
