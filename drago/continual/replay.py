"""Bounded replay across tasks (paper §4, the paper's "replay-based MBRL with a bounded buffer").

A reservoir of single transitions (s, a, s') is kept across tasks, capped at the memory of DRAGO's
generative model: the grid VAE's 21,638 parameters hold ~2,163 grid transitions at 10 floats per
transition (docs: Methods, replay), the default of ``method.replay.capacity``. Every transition a task collected is offered to
the reservoir when the task ends, so during task k it holds a uniform sample of tasks 1..k-1 and the
world-model objective mixes those old rows with the task's own sequences.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import nn

from drago.agent.buffer import EpisodeReplay
from drago.agent.losses import prediction_error
from drago.agent.protocol import capabilities_of
from drago.config import Config
from drago.continual.base import ContinualMethod, TaskState
from drago.envs import EnvSpec
from drago.seeding import rng_state, set_rng_state


class ReservoirBuffer:
    """A fixed-capacity uniform sample of every transition ever offered (Vitter's algorithm R).

    The i-th transition offered (0-based, counted over all tasks) is stored directly while the buffer
    has room; afterwards it replaces a slot ``j ~ U{0..i}`` if ``j < capacity`` and is dropped otherwise.
    After ``n`` offers every one of them is held with the same probability ``capacity / n``, so each
    task keeps a share proportional to the data it offered, however long ago it ended.

    Each slot also records the index of the task that offered it (bookkeeping only; 9 floats of
    (s, a, s') plus this tag per grid transition stay within the budget of 10 numbers per transition).

    Args:
        capacity: the most transitions ever held.
        obs_dim: observation size.
        act_dim: action size.
        rng: source of the replacement draws; its state is part of :meth:`state_dict`.
        device: where the stored tensors (and sampled minibatches) live.
    """

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, rng: np.random.Generator,
                 device: str | torch.device = "cpu"):
        if capacity < 1:
            raise ValueError(f"reservoir capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.obs_dim = int(obs_dim)
        self.act_dim = int(act_dim)
        self.rng = rng
        self.device = torch.device(device)
        self.obs = torch.zeros(self.capacity, self.obs_dim, device=self.device)
        self.actions = torch.zeros(self.capacity, self.act_dim, device=self.device)
        self.next_obs = torch.zeros(self.capacity, self.obs_dim, device=self.device)
        self.tasks = torch.full((self.capacity,), -1, dtype=torch.long, device=self.device)
        self.seen = 0  # transitions ever offered

    def __len__(self) -> int:
        return min(self.seen, self.capacity)

    def offer(self, obs: torch.Tensor, actions: torch.Tensor, next_obs: torch.Tensor, task: int = 0) -> None:
        """Offer n transitions in order, exactly as n single steps of algorithm R would.

        The decision for the i-th offer depends only on i, never on what the buffer holds, so all
        decisions are drawn at once; when several offers of one call pick the same slot, the last one
        wins, as it would sequentially.

        Args:
            obs, actions, next_obs: (n, obs_dim), (n, act_dim), (n, obs_dim).
            task: index of the task the transitions come from.
        """
        n = int(obs.shape[0])
        if actions.shape != (n, self.act_dim) or obs.shape != (n, self.obs_dim) or next_obs.shape != obs.shape:
            raise ValueError(f"transition shapes {tuple(obs.shape)}, {tuple(actions.shape)}, "
                             f"{tuple(next_obs.shape)} do not match obs_dim {self.obs_dim}, act_dim {self.act_dim}")
        if n == 0:
            return
        fill = max(0, min(n, self.capacity - self.seen))  # offers that land in still-empty slots
        slots = np.arange(self.seen, self.seen + fill)
        items = np.arange(fill)
        if fill < n:
            global_index = np.arange(self.seen + fill, self.seen + n)  # i for each remaining offer
            draws = self.rng.integers(0, global_index + 1)  # j ~ U{0..i}
            keep = draws < self.capacity
            replaced, offered = draws[keep], np.arange(fill, n)[keep]
            # Last write wins: keep the final occurrence of each slot.
            last_first, position = np.unique(replaced[::-1], return_index=True)
            slots = np.concatenate([slots, last_first])
            items = np.concatenate([items, offered[::-1][position]])
        if slots.size:
            dst = torch.as_tensor(slots, dtype=torch.long, device=self.device)
            src = torch.as_tensor(items, dtype=torch.long, device=obs.device)
            self.obs[dst] = obs[src].to(self.device, torch.float32)
            self.actions[dst] = actions[src].to(self.device, torch.float32)
            self.next_obs[dst] = next_obs[src].to(self.device, torch.float32)
            self.tasks[dst] = int(task)
        self.seen += n

    def sample(self, n: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``n`` rows drawn uniformly with replacement: ``(obs, actions, next_obs)``."""
        if len(self) == 0:
            raise ValueError("cannot sample from an empty reservoir")
        idx = torch.as_tensor(rng.integers(0, len(self), size=n), dtype=torch.long, device=self.device)
        return self.obs[idx], self.actions[idx], self.next_obs[idx]

    def task_counts(self) -> dict[int, int]:
        """How many held transitions each task contributed."""
        tags = self.tasks[: len(self)].cpu()
        values, counts = torch.unique(tags, return_counts=True)
        return {int(v): int(c) for v, c in zip(values, counts)}

    def state_dict(self) -> dict[str, Any]:
        """Tensors (on CPU), ints and the rng state only, so checkpoints load with ``weights_only``."""
        size = len(self)
        return {"capacity": self.capacity, "obs_dim": self.obs_dim, "act_dim": self.act_dim, "seen": self.seen,
                "obs": self.obs[:size].cpu().clone(), "actions": self.actions[:size].cpu().clone(),
                "next_obs": self.next_obs[:size].cpu().clone(), "tasks": self.tasks[:size].cpu().clone(),
                "rng": rng_state(self.rng)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        mine = (self.capacity, self.obs_dim, self.act_dim)
        theirs = (int(state["capacity"]), int(state["obs_dim"]), int(state["act_dim"]))
        if theirs != mine:
            raise ValueError(f"reservoir (capacity, obs_dim, act_dim) mismatch: state {theirs}, buffer {mine}")
        self.seen = int(state["seen"])
        size = len(self)
        self.obs.zero_()
        self.actions.zero_()
        self.next_obs.zero_()
        self.tasks.fill_(-1)
        self.obs[:size] = state["obs"].to(self.device)
        self.actions[:size] = state["actions"].to(self.device)
        self.next_obs[:size] = state["next_obs"].to(self.device)
        self.tasks[:size] = state["tasks"].to(self.device)
        set_rng_state(self.rng, state["rng"])


def stored_transitions(buffer: EpisodeReplay) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every transition an episode buffer holds, as ``(obs, actions, next_obs)`` rows.

    Read through the buffer's public :meth:`EpisodeReplay.state_dict`: transition i of the flat layout
    is step ``i % L`` of episode slot ``i // L``, and s_L of each episode is kept apart.
    """
    state = buffer.state_dict()
    length = int(state["config"]["episode_length"])
    episodes = int(state["num_episodes"])
    rows = episodes * length
    obs = state["obs"][:rows].view(episodes, length, -1)
    nxt = torch.cat((obs[:, 1:], state["last_obs"][:episodes, None]), dim=1)
    return obs.reshape(rows, -1), state["actions"][:rows], nxt.reshape(rows, -1)


def replay_loss(world_model: nn.Module, obs: torch.Tensor, actions: torch.Tensor,
                next_obs: torch.Tensor) -> torch.Tensor:
    """One-step consistency loss ``mean_rows mse(d(h(s), a), h(s'))`` of replayed transitions, or the world
    model's own objective on them when it has one (``transition_loss``: PETS's ensemble NLL)."""
    own = getattr(world_model, "transition_loss", None)
    if own is not None:
        return own(obs, actions, next_obs)
    predicted = world_model(world_model.encode(obs), actions)
    return prediction_error(predicted, world_model.encode(next_obs)).mean()


def replay_weight(consistency_coef: float, horizon: int, fraction: float) -> float:
    """Weight of :func:`replay_loss` that makes old rows a ``fraction`` of the world-model batch.

    The learner's objective is ``mean_b(w_b * total_b) / H`` over its B new sequences, each of which
    gives the world model ``consistency_coef * sum_t rho^t mse_t``. Putting old rows in a share ``f`` of a
    larger batch would make the objective ``(1 - f) * (mean_new + f / (1 - f) * mean_old)``. The factor
    ``1 - f`` is dropped so the task's own rows keep exactly the weight they have in every other method
    (gradient clipping included); what remains adds ``f / (1 - f)`` times the old rows' mean. An old row
    is a single transition, a sequence of one step, so its loss is ``consistency_coef * mse / H``: the
    scale of a new sequence's first step. The old rows are sampled uniformly, so their weight is 1.

    Returns:
        ``consistency_coef * f / ((1 - f) * H)``.

    Raises:
        ValueError: ``f`` outside ``[0, 1)`` (a batch of old rows only has no new rows to weigh against).
    """
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"method.replay.fraction must lie in [0, 1) for replay, got {fraction}")
    return consistency_coef * fraction / ((1.0 - fraction) * horizon)


class Replay(ContinualMethod):
    """Continual TD-MPC that rehearses a bounded reservoir of old transitions in its world-model loss.

    The reservoir is filled at the end of each task from the whole task buffer (every transition the
    learner collected, in order), so it changes only at task boundaries: it is carried in the task
    checkpoint and a task resumed in its middle finds it exactly as the uninterrupted run had it.
    During a task it therefore holds only earlier tasks' data, which is what replay must protect.
    """

    name = "replay"
    reads = ("replay",)
    description = "continual TD-MPC with a bounded reservoir of old transitions mixed into world-model batches"

    def __init__(self, cfg: Config, spec: EnvSpec, device: torch.device):
        super().__init__(cfg, spec, device)
        # A PETS ensemble's objective is its NLL averaged over single transitions with coefficient 1 (docs:
        # Methods, PETS): there an old transition weighs as a one-step sequence of coefficient 1.
        sequences = capabilities_of(cfg.agent.kind).sequence_loss
        coef, steps = (cfg.agent.tdmpc.consistency_coef, cfg.agent.tdmpc.horizon) if sequences else (1.0, 1)
        self.weight = replay_weight(coef, steps, cfg.method.replay.fraction)
        # Own generator: the reservoir's draws never disturb the task's sampling stream.
        rng = np.random.default_rng(np.random.SeedSequence([cfg.train.seed, 0x5E5E7]))
        self.reservoir = ReservoirBuffer(cfg.method.replay.capacity, spec.obs_dim, spec.action_dim, rng, device)

    def world_model_loss(self, task: TaskState) -> Callable[[], torch.Tensor] | None:
        if not len(self.reservoir) or self.weight <= 0:
            return None
        old = self.reservoir.sample(self.cfg.agent.batch_size, task.rng)
        return lambda: self.weight * replay_loss(task.world_model, *old)

    def end_task(self, task: TaskState) -> None:
        # The task buffer holds every transition of the task unless the task outgrew it (more than
        # MAX_BUFFER steps): then only the latest ones reach the reservoir.
        self.reservoir.offer(*stored_transitions(task.buffer), task=task.index)

    def carry_state(self) -> dict[str, Any]:
        return {"reservoir": self.reservoir.state_dict()}

    def load_carry_state(self, state: dict[str, Any]) -> None:
        self.reservoir.load_state_dict(state["reservoir"])
