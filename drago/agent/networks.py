"""Networks of the TD-MPC agent (paper §2; docs: Design, the agent): the shared world model and the task-specific heads.

The world model and the heads are separate modules on purpose. A continual method carries the
:class:`WorldModel` from task to task and builds fresh :class:`TaskHeads` for every task; DRAGO's
learner and reviewer are two ``TaskHeads`` over one ``WorldModel``.
"""

from __future__ import annotations

import contextlib
import copy

import torch
import torch.nn.functional as F
from torch import nn

from drago.config import Config
from drago.envs import EnvSpec

# The dynamics output is clamped before squashing, as in the official code.
DYNAMICS_CLAMP = 100.0


def autocast(device: torch.device | str, precision: str) -> contextlib.AbstractContextManager:
    """The agent's reduced-precision context: bfloat16 autocast, or nothing for float32.

    Under it the hidden layers run in bfloat16 while every network's output layer stays in float32
    (:func:`_float32_output`), so predicted states, rewards and Q values, and with them the losses and
    TD targets built from them, keep float32 precision. Backward passes run outside the context.
    """
    if precision == "float32":
        return contextlib.nullcontext()
    if precision != "bfloat16":
        raise ValueError(f"unknown precision '{precision}'; valid: float32, bfloat16 (a run resolves auto, see "
                         "drago.agent.speed)")
    return torch.autocast(device_type=torch.device(device).type, dtype=torch.bfloat16)


def _float32_output(x: torch.Tensor, layer) -> torch.Tensor:
    """Apply an output layer in float32 even under autocast.

    A bfloat16 output keeps 8 significant bits: a Q value near 200 would be rounded to a multiple of 1,
    a value of the order of the TD errors the critics must fit. The layer's FLOPs are negligible.
    """
    if torch.is_autocast_enabled(x.device.type):
        with torch.autocast(device_type=x.device.type, enabled=False):
            return layer(x.float())
    return layer(x)


def _tanh_from_sigmoid(x: torch.Tensor) -> torch.Tensor:
    """tanh(x) = 2·sigmoid(2x) − 1.

    torch's CPU tanh does not vectorise on every machine, where it costs many times a sigmoid (docs:
    Benchmarks). The identity agrees with ``torch.tanh`` to 3e-7, but not bit for bit.
    """
    return torch.sigmoid(x * 2).mul_(2).sub_(1)


class _SigmoidTanh(torch.autograd.Function):
    """:func:`_tanh_from_sigmoid` with tanh's own backward, from the output."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        y = _tanh_from_sigmoid(x)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)


def tanh(x: torch.Tensor, fast: bool) -> torch.Tensor:
    """``torch.tanh``, or with ``fast`` its sigmoid form (``agent.tdmpc.fast_tanh``, see :func:`_tanh_from_sigmoid`)."""
    if not fast:
        return torch.tanh(x)
    if torch.is_grad_enabled() and x.requires_grad:
        return _SigmoidTanh.apply(x)
    return _tanh_from_sigmoid(x)


class CReLU(nn.Module):
    """concat(ReLU(x), ReLU(-x)): keeps both signs alive, which doubles the width."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat((F.relu(x), F.relu(-x)), dim=-1)


class OutputLinear(nn.Linear):
    """The last layer of a network: an ``nn.Linear`` that computes in float32 under autocast."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _float32_output(x, super().forward)


def _init_linear(layer: nn.Linear, zero: bool = False) -> None:
    if zero:
        nn.init.zeros_(layer.weight)
    else:
        nn.init.orthogonal_(layer.weight, gain=1.0)
    nn.init.zeros_(layer.bias)


def mlp(in_dim: int, hidden: int, out_dim: int, act: str = "elu", zero_last: bool = False) -> nn.Sequential:
    """Linear - act - Linear - act - Linear with orthogonal weights and zero biases.

    Args:
        act: ``elu`` or ``crelu`` (CReLU doubles the width seen by the following layer).
        zero_last: zero the last layer, so reward and value heads start at exactly 0.
    """
    width = 2 * hidden if act == "crelu" else hidden
    make_act = CReLU if act == "crelu" else nn.ELU
    layers = [nn.Linear(in_dim, hidden), make_act(), nn.Linear(width, hidden), make_act(), OutputLinear(width, out_dim)]
    for i, layer in enumerate(layers):
        if isinstance(layer, nn.Linear):
            _init_linear(layer, zero=zero_last and i == len(layers) - 1)
    return nn.Sequential(*layers)


class WorldModel(nn.Module):
    """Identity encoder plus dynamics MLP predicting the next (raw) observation.

    With ``use_encoder=false`` (every experiment of the paper) the latent is the observation itself,
    so the world model is the dynamics network alone. It keeps an EMA target copy, updated with the
    heads' targets, so checkpoints carry the same state as the official code's.
    """

    def __init__(self, obs_dim: int, action_dim: int, mlp_dim: int, use_crelu: bool, squash: bool):
        super().__init__()
        self.obs_dim = obs_dim
        self.action_dim = action_dim
        self.squash = squash
        self.dynamics = mlp(obs_dim + action_dim, mlp_dim, obs_dim, act="crelu" if use_crelu else "elu")
        self.target = copy.deepcopy(self.dynamics).requires_grad_(False)

    def encode(self, obs: torch.Tensor) -> torch.Tensor:
        """The latent of an observation (identity: the paper never enables the encoder)."""
        return obs

    def raw_next(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Pre-clamp, pre-squash output: what synthetic rehearsal distils (paper §3.1)."""
        return self.dynamics(torch.cat((z, action), dim=-1))

    def squash_output(self, raw: torch.Tensor) -> torch.Tensor:
        out = raw.clamp(-DYNAMICS_CLAMP, DYNAMICS_CLAMP)
        return torch.tanh(out) if self.squash else out

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Predicted next latent, exactly as the planner sees it."""
        return self.squash_output(self.raw_next(z, action))

    @torch.no_grad()
    def ema_update(self, tau: float) -> None:
        for p, p_target in zip(self.dynamics.parameters(), self.target.parameters()):
            p_target.lerp_(p, tau)


class EnsembleLinear(nn.Module):
    """``n`` independent linear layers evaluated as one batched matmul.

    Args:
        output: the network's last layer, computed in float32 under autocast (see :class:`OutputLinear`).
    """

    def __init__(self, n: int, in_dim: int, out_dim: int, zero: bool = False, output: bool = False):
        super().__init__()
        self.output = output
        self.weight = nn.Parameter(torch.empty(n, in_dim, out_dim))
        self.bias = nn.Parameter(torch.zeros(n, 1, out_dim))
        for i in range(n):
            if zero:
                nn.init.zeros_(self.weight.data[i])
            else:
                # Orthogonal init of the (out, in) matrix, as for nn.Linear, stored transposed.
                w = torch.empty(out_dim, in_dim)
                nn.init.orthogonal_(w, gain=1.0)
                self.weight.data[i] = w.t()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _float32_output(x, self._forward) if self.output else self._forward(x)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        # x: (n, rows, in) or (rows, in) broadcast to every member.
        if x.dim() == 2:
            return torch.baddbmm(self.bias, x.unsqueeze(0).expand(self.weight.shape[0], -1, -1), self.weight)
        return torch.baddbmm(self.bias, x, self.weight)


class TwinQ(nn.Module):
    """Two critics Linear - LayerNorm - Tanh - Linear - ELU - Linear, batched as one ensemble."""

    def __init__(self, in_dim: int, mlp_dim: int, fast_tanh: bool = False):
        super().__init__()
        self.fast_tanh = fast_tanh
        self.l1 = EnsembleLinear(2, in_dim, mlp_dim)
        self.ln_weight = nn.Parameter(torch.ones(2, 1, mlp_dim))
        self.ln_bias = nn.Parameter(torch.zeros(2, 1, mlp_dim))
        self.l2 = EnsembleLinear(2, mlp_dim, mlp_dim)
        self.l3 = EnsembleLinear(2, mlp_dim, 1, zero=True, output=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Returns (2, rows) values for inputs of shape (rows, in_dim)."""
        h = self.l1(x)
        h = F.layer_norm(h, h.shape[-1:]) * self.ln_weight + self.ln_bias
        h = F.elu(self.l2(tanh(h, self.fast_tanh)))
        return self.l3(h).squeeze(-1)


class TaskHeads(nn.Module):
    """Reward, policy and twin Q of one agent for one task, plus the EMA target of Q.

    Inputs to the reward head and the critics are detached from the world model, so only the
    consistency loss and rehearsal can change the dynamics (paper §2; docs: Design, the agent, gradient isolation).
    """

    def __init__(self, obs_dim: int, action_dim: int, mlp_dim: int, discrete: bool, fast_tanh: bool = False):
        super().__init__()
        self.discrete = discrete
        self.fast_tanh = fast_tanh
        self.action_dim = action_dim
        self.reward = mlp(obs_dim + action_dim, mlp_dim, 1, zero_last=True)
        self.policy = mlp(obs_dim, mlp_dim, action_dim)
        self.q = TwinQ(obs_dim + action_dim, mlp_dim, fast_tanh)
        self.q_target = copy.deepcopy(self.q).requires_grad_(False)

    def predict_reward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.reward(torch.cat((z.detach(), action), dim=-1)).squeeze(-1)

    def q_values(self, z: torch.Tensor, action: torch.Tensor, target: bool = False) -> torch.Tensor:
        """(2, rows) twin-critic values; z is detached so critics never train the world model."""
        net = self.q_target if target else self.q
        return net(torch.cat((z.detach(), action), dim=-1))

    def act(self, z: torch.Tensor, std: float, deterministic: bool = False) -> torch.Tensor:
        """Policy action (paper §2; docs: Design, the agent): hard Gumbel one-hot for the grid, clipped Gaussian around tanh(mu)."""
        out = self.policy(z)
        if self.discrete:
            if deterministic:
                return F.one_hot(out.argmax(-1), self.action_dim).to(out.dtype)
            return F.gumbel_softmax(out, tau=1.0, hard=True)
        mu = tanh(out, self.fast_tanh)
        if deterministic or std <= 0:
            return mu
        noise = (std * torch.randn_like(mu)).clamp(-0.3, 0.3)
        sample = mu + noise
        clamped = sample.clamp(-1 + 1e-6, 1 - 1e-6)
        # Straight-through: clamp in the forward pass, identity gradient.
        return sample + (clamped - sample).detach()

    @torch.no_grad()
    def ema_update(self, tau: float) -> None:
        for p, p_target in zip(self.q.parameters(), self.q_target.parameters()):
            p_target.lerp_(p, tau)


def build_world_model(cfg: Config, spec: EnvSpec, device: torch.device | str = "cpu") -> WorldModel:
    """The world model a run of ``cfg`` on a domain of ``spec`` trains (and its checkpoints hold)."""
    # The grid's observations lie in [-1, 1]: its dynamics end in tanh (paper Appendix A).
    return WorldModel(spec.obs_dim, spec.action_dim, cfg.agent.tdmpc.mlp_dim, cfg.agent.tdmpc.use_crelu,
                      squash=spec.discrete).to(device)


def linear_schedule(start: float, end: float, duration: int, step: int) -> float:
    """Linear interpolation from ``start`` to ``end`` over ``duration`` steps, then constant."""
    mix = min(max(step / duration, 0.0), 1.0)
    return start + mix * (end - start)


def parameter_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
