"""Checkpoints: written atomically, versioned, and checked on load with one-line errors.

Two kinds live in a run's ``checkpoints/`` folder:

* ``task<k>_<name>.pt``: written at the end of task k. It holds the world model, the method's carried
  state (VAE, threshold, ...) and, separately, the learner's heads. The next task reads only the
  world model and the carried state (spec §3.10, ``load_policy=false``).
* ``resume.pt``: the latest periodic snapshot of the task in progress, with everything needed to go on
  (optimizers, buffer, RNG states, log positions).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

FORMAT = "drago-checkpoint"
VERSION = 1
KINDS = ("task", "resume")


class CheckpointError(ValueError):
    """A missing, corrupt or incompatible checkpoint; the message is one line."""


def save_checkpoint(path: str | Path, payload: dict[str, Any], kind: str, domain: str) -> Path:
    """Write ``payload`` so that a crash at any moment leaves either the old file or the new one.

    The data goes to a temporary file in the same folder, is flushed to disk, and then replaces the
    target with an atomic rename.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown checkpoint kind '{kind}'; valid kinds: {', '.join(KINDS)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"format": FORMAT, "version": VERSION, "kind": kind, "domain": domain, **payload}
    # A process killed mid-write leaves its temporary file behind; the next save clears it.
    for stale in path.parent.glob(f".{path.name}.*.tmp"):
        stale.unlink(missing_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            torch.save(data, handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates owner-only files; checkpoints are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    return path


def load_checkpoint(path: str | Path, kind: str | None = None, domain: str | None = None,
                    map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read and check a checkpoint written by :func:`save_checkpoint`.

    Raises:
        CheckpointError: missing file, unreadable or foreign content, newer format version, wrong
            kind, or a checkpoint of another domain.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        # Only tensors and plain Python values are stored, so nothing executable is ever unpickled.
        data = torch.load(path, map_location=map_location, weights_only=True)
    except Exception:
        # Damaged bytes surface as whatever the unpickler trips on first (struct.error for a few bytes of
        # text, UnicodeDecodeError, ...); any failure to read means the same thing. torch's own message
        # advises loosening weights_only, which is the wrong advice here.
        raise CheckpointError(f"checkpoint {path} is corrupt or not a drago checkpoint; "
                              "delete it to redo that part of the run") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a drago checkpoint")
    if data.get("version", 0) > VERSION:
        raise CheckpointError(f"{path} has format version {data['version']}, newer than this drago "
                              f"(reads <= {VERSION}); upgrade drago")
    if kind is not None and data.get("kind") != kind:
        raise CheckpointError(f"{path} is a '{data.get('kind')}' checkpoint, expected '{kind}'")
    if domain is not None and data.get("domain") != domain:
        raise CheckpointError(f"{path} comes from domain '{data.get('domain')}', but this run is '{domain}'")
    return data


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


def task_checkpoint_path(run_dir: str | Path, tasks: tuple[str, ...] | list[str], stage: int) -> Path:
    """Where a run saves its state after its ``stage``-th task (1-based): ``checkpoints/task<k>_<name>.pt``."""
    return Path(run_dir) / "checkpoints" / f"task{stage}_{tasks[stage - 1]}.pt"


@contextlib.contextmanager
def seeded_torch_rng(seed: int, device: torch.device | str = "cpu") -> Iterator[None]:
    """Run a block on torch's global generator seeded with ``seed``, then restore the previous state.

    The planner draws from the global generator; this gives a block (an evaluation, a pre-rollout, a
    held-out recording) its own reproducible stream without moving the one training continues with.
    """
    device = torch.device(device)
    cuda = [device.index if device.index is not None else torch.cuda.current_device()] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=cuda):
        torch.default_generator.manual_seed(int(seed))
        for index in cuda:
            with torch.cuda.device(index):
                torch.cuda.manual_seed(int(seed))
        yield
