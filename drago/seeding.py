"""Reproducible random streams: every (run seed, task, purpose) has its own, and side work never moves
the stream training continues with. Same seed, same CPU, same logs (docs: design, "Reproducibility")."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch


def task_seed(seed: int, task_index: int, *purpose: int) -> int:
    """Independent, reproducible seeds per (run seed, task, purpose): a resumed task replays exactly."""
    return int(np.random.SeedSequence([seed, task_index, *purpose]).generate_state(1)[0])


@contextlib.contextmanager
def seeded_torch_rng(seed: int, device: torch.device | str = "cpu") -> Iterator[None]:
    """Run a block on torch's global generator seeded with ``seed``, then restore the previous state.

    The planner draws from the global generator; this gives a block (an evaluation, a pre-rollout, a
    held-out recording, building a network to load weights into) its own reproducible stream without
    moving the one training continues with.
    """
    device = torch.device(device)
    cuda = [device.index if device.index is not None else torch.cuda.current_device()] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=cuda):
        torch.default_generator.manual_seed(int(seed))
        for index in cuda:
            with torch.cuda.device(index):
                torch.cuda.manual_seed(int(seed))
        yield


def rng_state(rng: np.random.Generator) -> dict[str, Any]:
    """A numpy generator's state as tensors and ints only, so checkpoints load with weights_only."""
    return _to_safe(rng.bit_generator.state)


def set_rng_state(rng: np.random.Generator, state: dict[str, Any]) -> None:
    rng.bit_generator.state = _from_safe(state)


def _to_safe(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _to_safe(v) for k, v in value.items()}
    if isinstance(value, int) and not isinstance(value, bool) and not -(2**63) <= value < 2**63:
        return {"__bigint__": str(value)}
    return value


def _from_safe(value: Any) -> Any:
    if isinstance(value, dict):
        if set(value) == {"__bigint__"}:
            return int(value["__bigint__"])
        return {k: _from_safe(v) for k, v in value.items()}
    return value
