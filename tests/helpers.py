"""Helpers shared by the test files (pytest puts this folder on the import path)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from drago.agent.buffer import EpisodeReplay

#: How the tests start runs: no progress bar, no TensorBoard files.
QUIET = ["--no-progress", "train.tensorboard=false"]


def read_csv(path: Path) -> list[dict[str, str]]:
    with Path(path).open(newline="") as handle:
        return list(csv.DictReader(handle))


def filled_buffer(device_priorities: bool, obs_dim: int = 3, act_dim: int = 2, horizon: int = 3,
                  length: int = 20, episodes: int = 6) -> EpisodeReplay:
    """A CPU replay buffer of random episodes, its priorities in the host or the device form."""
    buf = EpisodeReplay(200, obs_dim, act_dim, horizon, length, device="cpu", device_priorities=device_priorities)
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        buf.add_episode(rng.random((length + 1, obs_dim)), rng.random((length, act_dim)), rng.random(length))
    return buf
