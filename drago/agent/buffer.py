"""Prioritized episode replay buffer (paper §2; docs: Design, the agent).

The buffer stores fixed-length episodes and samples (H+1)-long sequences
with prioritized experience replay. On the CPU, priorities live in a
vectorised numpy sum tree so that sampling and priority write-back cost
O(B log N) instead of the O(N) of TD-MPC's dense ``probs = p**alpha / sum``
approach. On an accelerator they stay on the device (:class:`DevicePriorities`):
the next batch depends on the priorities the last update computed, and a host
tree would make every gradient step wait for the device twice (priorities to
the host, indices and weights back).
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

ArrayLike = np.ndarray | torch.Tensor

__all__ = ["Batch", "DevicePriorities", "EpisodeReplay", "HostPriorities", "NonFinitePriority", "Priorities", "SumTree"]


class SumTree:
    """Array-backed binary sum tree over non-negative leaf values.

    The tree is a complete binary tree stored 1-indexed in a flat float64
    array: the root is node 1, node ``k`` has children ``2k`` and ``2k+1`` and
    the leaves occupy ``[P, 2P)`` where ``P`` is ``capacity`` rounded up to a
    power of two. Padding leaves stay zero and are therefore never returned
    by :meth:`find`. All operations are vectorised over a batch of leaves.

    Args:
        capacity: Number of usable leaves (>= 1).
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"SumTree capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self._num_leaves = 1 << max(0, (self.capacity - 1).bit_length())
        self._depth = self._num_leaves.bit_length() - 1
        self._tree = np.zeros(2 * self._num_leaves, dtype=np.float64)
        self._max = 0.0

    @property
    def total(self) -> float:
        """Sum of all leaf values."""
        return float(self._tree[1])

    @property
    def max(self) -> float:
        """Running maximum of every value ever written to a leaf.

        It never decreases, matching TD-MPC's ``priority_max``; it is meant
        as the priority for new insertions, not as the exact current max.
        """
        return self._max

    def _check_indices(self, indices: np.ndarray) -> np.ndarray:
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.capacity):
            raise IndexError(f"SumTree leaf index out of range [0, {self.capacity})")
        return idx

    def update(self, indices: np.ndarray, values: np.ndarray) -> None:
        """Set leaf values and refresh their ancestors.

        With duplicate indices the last occurrence wins. Parents are recomputed
        as ``left + right`` rather than adjusted by deltas, so no floating-point
        drift accumulates over millions of updates.

        Args:
            indices: Leaf indices, shape (n,).
            values: New non-negative finite values, shape (n,) or scalar.
        """
        idx = self._check_indices(indices)
        vals = np.broadcast_to(np.asarray(values, dtype=np.float64), idx.shape)
        if idx.size == 0:
            return
        if not np.all(np.isfinite(vals)) or np.any(vals < 0):
            raise ValueError("SumTree values must be finite and non-negative")
        # Keep the last write for duplicated leaves (numpy's fancy assignment
        # order with duplicates is not a documented guarantee).
        rev_unique, rev_pos = np.unique(idx[::-1], return_index=True)
        vals = vals[::-1][rev_pos]
        idx = rev_unique
        nodes = idx + self._num_leaves
        self._tree[nodes] = vals
        self._max = max(self._max, float(vals.max()))
        for _ in range(self._depth):
            nodes = np.unique(nodes >> 1)
            self._tree[nodes] = self._tree[2 * nodes] + self._tree[2 * nodes + 1]

    def values(self, indices: np.ndarray) -> np.ndarray:
        """Return leaf values for ``indices`` (float64 array of the same shape)."""
        idx = np.asarray(indices, dtype=np.int64)
        flat = self._check_indices(idx)
        return self._tree[flat + self._num_leaves].reshape(idx.shape)

    def __getitem__(self, indices: np.ndarray | int) -> np.ndarray | float:
        if np.isscalar(indices):
            return float(self.values(np.asarray([indices]))[0])
        return self.values(np.asarray(indices))

    def find(self, prefix_sums: np.ndarray) -> np.ndarray:
        """Find, for each prefix value v, the leaf i with cumsum_{<i} <= v < cumsum_{<=i}.

        Values are clipped into ``[0, total]``. The descent never enters a
        zero-sum subtree, so a positive-valued leaf is always returned when
        ``total > 0`` even if rounding pushes ``v`` past the last boundary.

        Args:
            prefix_sums: Prefix values, shape (n,).

        Returns:
            Leaf indices, int64 array of shape (n,).
        """
        if self.total <= 0.0:
            raise ValueError("SumTree.find called on a tree whose total is 0")
        v = np.clip(np.asarray(prefix_sums, dtype=np.float64).reshape(-1), 0.0, self.total)
        node = np.ones(v.shape, dtype=np.int64)
        for _ in range(self._depth):
            left = self._tree[2 * node]
            right = self._tree[2 * node + 1]
            go_right = (v >= left) & (right > 0.0)
            v = np.where(go_right, v - left, v)
            node = 2 * node + go_right
        return node - self._num_leaves

    def state_dict(self) -> dict[str, Any]:
        """Return a copy of the tree state."""
        # A tensor, not an ndarray, so checkpoints load with torch.load(weights_only=True).
        return {"capacity": self.capacity, "tree": torch.from_numpy(self._tree.copy()), "max": self._max}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state produced by :meth:`state_dict` of an equal-capacity tree."""
        if int(state["capacity"]) != self.capacity:
            raise ValueError(
                f"SumTree capacity mismatch: state {state['capacity']}, tree {self.capacity}"
            )
        tree = torch.as_tensor(state["tree"], dtype=torch.float64).numpy()
        if tree.shape != self._tree.shape:
            raise ValueError("SumTree state has the wrong array shape")
        self._tree[:] = tree
        self._max = float(state["max"])


class NonFinitePriority(ValueError):
    """A priority write-back with a NaN, an infinity or a negative value: the losses have diverged."""


class Priorities(ABC):
    """PER priorities of a buffer's transitions, behind one small interface with a host and a device form.

    A raw priority ``p`` is stored as ``(p + 1e-6) ** alpha``; new transitions get the largest raw
    priority seen so far; the last ``horizon`` steps of each episode keep priority 0, so every sampled
    start has its whole (H+1)-long sequence inside one episode.

    Args:
        capacity: Number of transitions.
        episode_length: L.
        horizon: H.
        alpha: PER priority exponent.
    """

    PRIORITY_EPS = 1e-6

    def __init__(self, capacity: int, episode_length: int, horizon: int, alpha: float) -> None:
        self.capacity, self.episode_length, self.horizon, self.alpha = capacity, episode_length, horizon, alpha

    @abstractmethod
    def add_episode(self, start: int) -> None:
        """Give the episode stored from flat index ``start`` the insertion priority."""

    @abstractmethod
    def draw(self, batch_size: int, rng: np.random.Generator, size: int,
             beta: float) -> tuple[torch.Tensor, torch.Tensor, np.ndarray | torch.Tensor]:
        """A stratified draw of ``batch_size`` starts among ``size`` stored transitions.

        Returns:
            (starts as a long tensor on the device, normalised importance weights, the indices to write
            priorities back to: numpy on the host, a device tensor on the device).
        """

    @abstractmethod
    def update(self, indices: ArrayLike, priorities: ArrayLike) -> None:
        """Write back raw priorities of sampled starts; starts in an episode's last H steps are ignored."""

    @abstractmethod
    def values(self, indices: ArrayLike) -> np.ndarray:
        """The stored values ``(p + 1e-6) ** alpha``."""

    @property
    @abstractmethod
    def max_priority(self) -> float:
        """Raw priority assigned to newly inserted transitions."""

    @abstractmethod
    def state_dict(self) -> dict[str, Any]:
        """``{"tree": ..., "max_priority": float}``."""

    @abstractmethod
    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what either form's :meth:`state_dict` saved (a run may resume on another device)."""

    def _sampleable(self, idx: ArrayLike) -> ArrayLike:
        return (idx % self.episode_length) < self.episode_length - self.horizon


class HostPriorities(Priorities):
    """Priorities in a host :class:`SumTree`: a draw and a write-back cost O(B log N) (the CPU default)."""

    def __init__(self, capacity: int, episode_length: int, horizon: int, alpha: float,
                 device: torch.device) -> None:
        super().__init__(capacity, episode_length, horizon, alpha)
        self.device = device
        self._tree = SumTree(capacity)
        self._max_priority = 1.0

    @property
    def max_priority(self) -> float:
        return self._max_priority

    def add_episode(self, start: int) -> None:
        L = self.episode_length
        prio = np.full(L, self._max_priority**self.alpha, dtype=np.float64)
        prio[L - self.horizon :] = 0.0
        self._tree.update(np.arange(start, start + L), prio)

    def draw(self, batch_size: int, rng: np.random.Generator, size: int,
             beta: float) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        total = self._tree.total
        segment = total / batch_size
        u = (np.arange(batch_size) + rng.random(batch_size)) * segment
        idx = self._tree.find(u)
        probs = self._tree.values(idx) / total
        weights = (size * probs) ** (-beta)
        weights /= weights.max()
        return (torch.as_tensor(idx, dtype=torch.long, device=self.device),
                torch.as_tensor(weights, dtype=torch.float32, device=self.device), idx)

    def update(self, indices: ArrayLike, priorities: ArrayLike) -> None:
        if isinstance(indices, torch.Tensor):
            indices = indices.detach().cpu().numpy()
        if isinstance(priorities, torch.Tensor):
            priorities = priorities.detach().to(torch.float64).cpu().numpy()
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        p = np.asarray(priorities, dtype=np.float64).reshape(-1)
        if idx.shape != p.shape:
            raise ValueError(f"indices {idx.shape} and priorities {p.shape} differ in shape")
        if not np.all(np.isfinite(p)) or np.any(p < 0):
            raise NonFinitePriority("priorities must be finite and non-negative")
        keep = self._sampleable(idx)
        idx, p = idx[keep], p[keep] + self.PRIORITY_EPS
        if idx.size == 0:
            return
        self._tree.update(idx, p**self.alpha)
        self._max_priority = max(self._max_priority, float(p.max()))

    def values(self, indices: ArrayLike) -> np.ndarray:
        if isinstance(indices, torch.Tensor):
            indices = indices.detach().cpu().numpy()
        return self._tree.values(np.asarray(indices, dtype=np.int64))

    def state_dict(self) -> dict[str, Any]:
        return {"tree": self._tree.state_dict(), "max_priority": float(self._max_priority)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        tree = state["tree"]
        if "leaves" in tree:  # saved with device priorities
            self._tree = SumTree(self.capacity)
            self._tree.update(np.arange(self.capacity), _leaves_of(tree))
        else:
            self._tree.load_state_dict(tree)
        self._max_priority = float(state["max_priority"])


class DevicePriorities(Priorities):
    """Priorities as a dense float64 tensor on the buffer's device (the default off the CPU).

    The next batch depends on the priorities the last update computed; a host tree would make every
    gradient step wait for the device twice (priorities to the host, indices and weights back). Here a
    draw is one cumulative sum over the leaves plus a binary search, both on the device, which is cheap
    there even at a million leaves, and nothing reads a value on the host. The contract is the host
    tree's: a stratified draw never returns a zero-valued leaf, and the last write wins for a duplicated
    index.
    """

    def __init__(self, capacity: int, episode_length: int, horizon: int, alpha: float,
                 device: torch.device) -> None:
        super().__init__(capacity, episode_length, horizon, alpha)
        self.device = device
        # One slot past the leaves receives the writes to drop (duplicates, ignored indices).
        self._values = torch.zeros(self.capacity + 1, dtype=torch.float64, device=device)
        # A device scalar, never read in the hot loop.
        self._max = torch.ones((), dtype=torch.float64, device=device)

    @property
    def max_priority(self) -> float:
        return float(self._max)

    def _write(self, indices: torch.Tensor, values: torch.Tensor, keep: torch.Tensor | None = None) -> None:
        idx = indices.reshape(-1)
        vals = values.reshape(-1).to(torch.float64)
        if idx.numel() == 0:
            return
        ordered, order = torch.sort(idx, stable=True)
        last = torch.ones_like(ordered, dtype=torch.bool)
        last[:-1] = ordered[1:] != ordered[:-1]
        if keep is not None:
            last &= keep.reshape(-1)[order]
        # Every kept index is now unique, so the write is deterministic; the rest land in the spare slot.
        self._values[torch.where(last, ordered, self.capacity)] = vals[order]

    def _leaves(self) -> torch.Tensor:
        return self._values[: self.capacity]

    def add_episode(self, start: int) -> None:
        L = self.episode_length
        prio = (self._max**self.alpha).expand(L).clone()
        prio[L - self.horizon :] = 0.0
        self._write(torch.arange(start, start + L, device=self.device), prio)

    def draw(self, batch_size: int, rng: np.random.Generator, size: int,
             beta: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # The same uniforms as the host form, copied without waiting for queued device work.
        uniforms = torch.from_numpy(rng.random(batch_size))
        if self.device.type == "cuda":
            uniforms = uniforms.pin_memory()
        uniforms = uniforms.to(self.device, non_blocking=True)
        cdf = torch.cumsum(self._leaves(), 0)
        total = cdf[-1]
        u = (torch.arange(batch_size, dtype=torch.float64, device=self.device) + uniforms) * (total / batch_size)
        # Strictly below the total, so the search always lands on a leaf with a positive value.
        u = torch.minimum(u, torch.nextafter(total, torch.zeros_like(total)))
        idx = torch.searchsorted(cdf, u, right=True)
        weights = (size * (self._values[idx] / total)) ** (-beta)
        return idx, (weights / weights.max()).to(torch.float32), idx

    def update(self, indices: ArrayLike, priorities: ArrayLike) -> None:
        """Without a host read: masks instead of filtering, and an asynchronous check."""
        idx = torch.as_tensor(indices, dtype=torch.long, device=self.device).reshape(-1)
        p = torch.as_tensor(priorities, device=self.device).detach().to(torch.float64).reshape(-1)
        if idx.shape != p.shape:
            raise ValueError(f"indices {tuple(idx.shape)} and priorities {tuple(p.shape)} differ in shape")
        if idx.numel() == 0:
            return
        # Raises at once on the CPU; on a GPU a failure surfaces at a later kernel launch.
        torch._assert_async(torch.all(torch.isfinite(p) & (p >= 0)), "priorities must be finite and non-negative")
        keep = self._sampleable(idx)
        p = p + self.PRIORITY_EPS
        self._write(idx, p**self.alpha, keep)
        self._max = torch.maximum(self._max, torch.where(keep, p, 0.0).max())

    def values(self, indices: ArrayLike) -> np.ndarray:
        return self._values[torch.as_tensor(indices, dtype=torch.long, device=self.device)].cpu().numpy()

    def state_dict(self) -> dict[str, Any]:
        return {"tree": {"capacity": self.capacity, "leaves": self._leaves().detach().cpu().clone()},
                "max_priority": float(self._max)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        tree = state["tree"]
        if int(tree["capacity"]) != self.capacity:
            raise ValueError(f"priority capacity mismatch: state {tree['capacity']}, buffer {self.capacity}")
        self._values.zero_()
        self._values[: self.capacity] = torch.as_tensor(_leaves_of(tree), dtype=torch.float64)
        self._max = torch.tensor(float(state["max_priority"]), dtype=torch.float64, device=self.device)


def _leaves_of(state: dict[str, Any]) -> np.ndarray:
    """Leaf values of a saved :class:`SumTree` or :class:`DevicePriorities` (a run resumed elsewhere)."""
    if "leaves" in state:
        return torch.as_tensor(state["leaves"], dtype=torch.float64).numpy()
    tree = torch.as_tensor(state["tree"], dtype=torch.float64).numpy()
    first = tree.shape[0] // 2
    return tree[first : first + int(state["capacity"])]


@dataclass
class Batch:
    """A PER batch of (H+1)-long sequences.

    Attributes:
        obs: Start observations s_0, shape (B, obs_dim).
        actions: a_t for t = 0..H, shape (H+1, B, act_dim).
        rewards: r_t for t = 0..H, shape (H+1, B).
        next_obs: s_{t+1} for t = 0..H, shape (H+1, B, obs_dim).
        weights: Normalised PER importance weights, shape (B,).
        indices: Sampled start indices, shape (B,), for priority write-back:
            numpy int64 from a CPU buffer, an int64 tensor on the device from
            a buffer with device priorities.
    """

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    weights: torch.Tensor
    indices: np.ndarray | torch.Tensor

    @property
    def batch_size(self) -> int:
        """Number of sequences B."""
        return int(self.obs.shape[0])

    def concat(self, other: Batch) -> Batch:
        """Concatenate two batches along the batch dimension (self first).

        Args:
            other: Batch with the same horizon and feature sizes.

        Returns:
            A new batch of size ``self.batch_size + other.batch_size``.
        """
        return Batch(
            obs=torch.cat([self.obs, other.obs], dim=0),
            actions=torch.cat([self.actions, other.actions], dim=1),
            rewards=torch.cat([self.rewards, other.rewards], dim=1),
            next_obs=torch.cat([self.next_obs, other.next_obs], dim=1),
            weights=torch.cat([self.weights, other.weights], dim=0),
            indices=(torch.cat([self.indices, other.indices]) if isinstance(self.indices, torch.Tensor)
                     else np.concatenate([self.indices, other.indices])),
        )

    def with_rewards(self, rewards: torch.Tensor) -> Batch:
        """Return a shallow copy with ``rewards`` replaced.

        Args:
            rewards: New rewards, shape (H+1, B).
        """
        if tuple(rewards.shape) != tuple(self.rewards.shape):
            raise ValueError(
                f"rewards shape {tuple(rewards.shape)} != {tuple(self.rewards.shape)}"
            )
        return dataclasses.replace(self, rewards=rewards)


class EpisodeReplay:
    """Prioritized replay of fixed-length episodes (paper §2; docs: Design, the agent).

    Transition ``i`` is stored at flat index ``i`` (episode slot ``i // L``,
    step ``i % L``); s_L of each episode is kept in a separate per-slot array.
    The last ``horizon`` steps of each episode get priority 0, so every
    sampled start t satisfies ``t + H <= L - 1`` and its whole sequence lies in
    one episode. Whole episodes are overwritten FIFO once the buffer is full.

    Sampling is stratified PER with replacement (also when full); TD-MPC
    samples without replacement once full, a quirk of the official code (docs: Design, paper and code).

    Args:
        capacity: Capacity in transitions, rounded down to whole episodes.
        obs_dim: Observation size.
        act_dim: Action size.
        horizon: H; sequences have H+1 steps.
        episode_length: L, steps per episode (must exceed ``horizon``).
        alpha: PER priority exponent.
        beta: PER importance-weight exponent.
        device: Torch device for the stored tensors and returned batches.
        device_priorities: keep priorities on ``device`` (:class:`DevicePriorities`)
            instead of in a host sum tree (:class:`HostPriorities`); None: on any device but the CPU.
    """

    def __init__(
        self,
        capacity: int,
        obs_dim: int,
        act_dim: int,
        horizon: int,
        episode_length: int,
        alpha: float = 0.6,
        beta: float = 0.4,
        device: str | torch.device = "cpu",
        device_priorities: bool | None = None,
    ) -> None:
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if episode_length <= horizon:
            raise ValueError(
                f"episode_length ({episode_length}) must exceed horizon ({horizon})"
            )
        if capacity < episode_length:
            raise ValueError(
                f"capacity ({capacity}) is smaller than one episode ({episode_length})"
            )
        self.obs_dim = int(obs_dim)
        self.act_dim = int(act_dim)
        self.horizon = int(horizon)
        self.episode_length = int(episode_length)
        self.alpha = float(alpha)
        self.beta = float(beta)
        self.device = torch.device(device)
        self.max_episodes = int(capacity) // self.episode_length
        self.capacity = self.max_episodes * self.episode_length

        self._obs = torch.zeros(
            self.capacity, self.obs_dim, dtype=torch.float32, device=self.device
        )
        self._last_obs = torch.zeros(
            self.max_episodes, self.obs_dim, dtype=torch.float32, device=self.device
        )
        self._actions = torch.zeros(
            self.capacity, self.act_dim, dtype=torch.float32, device=self.device
        )
        self._rewards = torch.zeros(self.capacity, dtype=torch.float32, device=self.device)
        if device_priorities is None:
            device_priorities = self.device.type != "cpu"
        kind = DevicePriorities if device_priorities else HostPriorities
        self._priorities: Priorities = kind(self.capacity, self.episode_length, self.horizon, self.alpha, self.device)
        self._next_slot = 0
        self._num_episodes = 0
        self._steps = torch.arange(self.horizon + 1, device=self.device)

    # ------------------------------------------------------------------ size
    def __len__(self) -> int:
        return self._num_episodes * self.episode_length

    @property
    def num_episodes(self) -> int:
        """Number of stored episodes."""
        return self._num_episodes

    def stored_states(self) -> torch.Tensor:
        """s_0..s_{L-1} of every stored episode, (episodes x L, obs_dim), in slot order (not by age once full)."""
        return self._obs[: self._num_episodes * self.episode_length]

    @property
    def is_full(self) -> bool:
        """Whether every episode slot holds data."""
        return self._num_episodes == self.max_episodes

    @property
    def device_priorities(self) -> bool:
        """Whether priorities live on the device (:class:`DevicePriorities`)."""
        return isinstance(self._priorities, DevicePriorities)

    @property
    def max_priority(self) -> float:
        """Raw priority assigned to newly inserted transitions."""
        return self._priorities.max_priority

    # ---------------------------------------------------------------- insert
    def _as_tensor(self, x: ArrayLike, name: str, shape: tuple[int, ...]) -> torch.Tensor:
        t = torch.as_tensor(x, dtype=torch.float32, device=self.device)
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {shape}")
        return t

    def add_episode(self, obs: ArrayLike, actions: ArrayLike, rewards: ArrayLike) -> None:
        """Append one episode, overwriting the oldest one when full.

        Args:
            obs: s_0..s_L, shape (L+1, obs_dim).
            actions: a_0..a_{L-1}, shape (L, act_dim).
            rewards: r_0..r_{L-1}, shape (L,).

        Raises:
            ValueError: If L <= horizon, L != episode_length or shapes mismatch.
        """
        length = int(np.shape(actions)[0]) if np.ndim(actions) > 0 else 0
        if length <= self.horizon:
            raise ValueError(f"episode length {length} must exceed horizon {self.horizon}")
        if length != self.episode_length:
            raise ValueError(
                f"episode length {length} != buffer episode_length {self.episode_length}"
            )
        L = self.episode_length
        obs_t = self._as_tensor(obs, "obs", (L + 1, self.obs_dim))
        act_t = self._as_tensor(actions, "actions", (L, self.act_dim))
        rew_t = self._as_tensor(rewards, "rewards", (L,))

        slot = self._next_slot
        start = slot * L
        self._obs[start : start + L] = obs_t[:L]
        self._last_obs[slot] = obs_t[L]
        self._actions[start : start + L] = act_t
        self._rewards[start : start + L] = rew_t

        self._priorities.add_episode(start)

        self._next_slot = (slot + 1) % self.max_episodes
        self._num_episodes = min(self._num_episodes + 1, self.max_episodes)

    # ---------------------------------------------------------------- sample
    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """Draw a stratified PER batch of (H+1)-long sequences.

        Args:
            batch_size: Number of sequences B.
            rng: Source of all randomness.

        Returns:
            A :class:`Batch` on the buffer's device.
        """
        if self._num_episodes == 0:
            raise ValueError("cannot sample from an empty buffer")
        starts, weights, idx = self._priorities.draw(batch_size, rng, len(self), self.beta)
        L = self.episode_length
        seq = starts.unsqueeze(0) + self._steps.unsqueeze(1)  # (H+1, B): t = 0..H
        nxt = seq + 1
        episode = starts // L
        # Only t = H of a start at step L-H-1 reaches s_L, which lives in _last_obs;
        # the modulo keeps the (masked-out) index in range for the last slot.
        at_end = nxt == (episode + 1).unsqueeze(0) * L
        next_obs = torch.where(
            at_end.unsqueeze(-1),
            self._last_obs[episode].unsqueeze(0),
            self._obs[nxt % self.capacity],
        )
        return Batch(
            obs=self._obs[starts],
            actions=self._actions[seq],
            rewards=self._rewards[seq],
            next_obs=next_obs,
            weights=weights,
            indices=idx,
        )

    def sample_transitions(
        self, n: int, rng: np.random.Generator
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Uniformly sample single (s, a) rows from the filled part.

        Args:
            n: Number of rows.
            rng: Source of randomness.

        Returns:
            ``(obs, actions)`` with shapes (n, obs_dim) and (n, act_dim).
        """
        if self._num_episodes == 0:
            raise ValueError("cannot sample from an empty buffer")
        rows = rng.integers(0, len(self), size=n)
        idx = torch.as_tensor(rows, dtype=torch.long, device=self.device)
        return self._obs[idx], self._actions[idx]

    # ------------------------------------------------------------ priorities
    def update_priorities(self, indices: ArrayLike, priorities: ArrayLike) -> None:
        """Write back new priorities for sampled starts.

        Stores ``(p + 1e-6) ** alpha`` and raises the insertion priority to
        the largest ``p + 1e-6`` seen. Indices in an episode's last H steps are
        ignored so those slots can never become sampleable.

        Args:
            indices: Start indices from :attr:`Batch.indices`, shape (n,).
            priorities: Non-negative raw priorities, shape (n,).
        """
        self._priorities.update(indices, priorities)

    def priorities(self, indices: ArrayLike) -> np.ndarray:
        """Return the stored values ``(p + 1e-6) ** alpha`` for ``indices``."""
        return self._priorities.values(indices)

    # ------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict[str, Any]:
        """Return a checkpointable copy of the buffer (tensors on CPU)."""
        return {
            "config": {
                "capacity": self.capacity,
                "obs_dim": self.obs_dim,
                "act_dim": self.act_dim,
                "horizon": self.horizon,
                "episode_length": self.episode_length,
            },
            "obs": self._obs.detach().cpu().clone(),
            "last_obs": self._last_obs.detach().cpu().clone(),
            "actions": self._actions.detach().cpu().clone(),
            "rewards": self._rewards.detach().cpu().clone(),
            **self._priorities.state_dict(),
            "next_slot": self._next_slot,
            "num_episodes": self._num_episodes,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state from :meth:`state_dict` of an identically configured buffer."""
        cfg = state["config"]
        mine = {
            "capacity": self.capacity,
            "obs_dim": self.obs_dim,
            "act_dim": self.act_dim,
            "horizon": self.horizon,
            "episode_length": self.episode_length,
        }
        if {k: int(cfg[k]) for k in mine} != mine:
            raise ValueError(f"buffer config mismatch: state {dict(cfg)} vs buffer {mine}")
        self._obs.copy_(state["obs"])
        self._last_obs.copy_(state["last_obs"])
        self._actions.copy_(state["actions"])
        self._rewards.copy_(state["rewards"])
        self._priorities.load_state_dict(state)
        self._next_slot = int(state["next_slot"])
        self._num_episodes = int(state["num_episodes"])
