"""Checkpoints: written atomically, versioned, and checked on load with one-line errors.

Two kinds live in a run's ``checkpoints/`` folder:

* ``task<k>_<name>.pt``: written at the end of task k. It holds the world model, the method's carried
  state (VAE, threshold, ...) and, separately, the learner's heads. The next task reads only the
  world model and the carried state (paper §3.3; docs: Design, how a run flows, ``load_policy=false``).
* ``resume.pt``: the latest periodic snapshot of the task in progress, with everything needed to go on
  (optimizers, buffer, RNG states, log positions).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from drago.agent.factory import build_world_model
from drago.agent.networks import WorldModel
from drago.agent.pets import PetsWorldModel
from drago.config import Config, ConfigError
from drago.envs import EnvSpec, env_spec
from drago.training.rundir import atomic_write
from drago.seeding import seeded_torch_rng

FORMAT = "drago-checkpoint"
VERSION = 1
KINDS = ("task", "resume")


class CheckpointError(ValueError):
    """A missing, corrupt or incompatible checkpoint; the message is one line."""


class NonFiniteCheckpoint(RuntimeError):
    """A checkpoint that would hold a NaN or an infinity in a floating-point tensor: it is never written."""


def _first_non_finite(value: Any, where: str = "") -> str | None:
    """The dotted key of the first floating-point tensor with a NaN or an infinity in a nested payload."""
    if isinstance(value, torch.Tensor):
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            return where or "a tensor"
        return None
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for key, inner in items:
        found = _first_non_finite(inner, f"{where}.{key}" if where else str(key))
        if found is not None:
            return found
    return None


def save_checkpoint(path: str | Path, payload: dict[str, Any], kind: str, domain: str) -> Path:
    """Write ``payload`` durably and atomically (:func:`~drago.training.rundir.atomic_write`): a crash at
    any moment leaves either the old file or the new one."""
    if kind not in KINDS:
        raise ValueError(f"unknown checkpoint kind '{kind}'; valid kinds: {', '.join(KINDS)}")
    bad = _first_non_finite(payload)
    if bad is not None:
        raise NonFiniteCheckpoint(f"not saving {path}: {bad} holds a non-finite value; the previous file is kept")
    data = {"format": FORMAT, "version": VERSION, "kind": kind, "domain": domain, **payload}
    return atomic_write(path, lambda handle: torch.save(data, handle), durable=True)


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


@dataclass
class TaskCheckpoint:
    """A task checkpoint, loaded: its raw contents, the config of the run that wrote it, and its world model.

    Attributes:
        path: the file.
        data: everything it stores (see the module docstring).
        config: the config of the run that wrote it.
        spec: its domain's sizes.
        world_model: the world model after the task, rebuilt from ``config`` (its ``agent.kind``) and loaded
            strictly.
    """

    path: Path
    data: dict[str, Any]
    config: Config
    spec: EnvSpec
    world_model: WorldModel | PetsWorldModel

    @property
    def task(self) -> str | None:
        return self.data.get("task")

    @property
    def task_index(self) -> int | None:
        index = self.data.get("task_index")
        return None if index is None else int(index)


def load_task_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> TaskCheckpoint:
    """Load a task checkpoint and rebuild its world model: the one loader behind the public API, transfers,
    pre-rollouts and every evaluation.

    Building the network draws initial weights from torch's global generator; that happens on a stream of
    its own, so loading a checkpoint in the middle of a run (a pre-rollout's learner, a held-out recording
    after a resume) leaves the training's stream where it was.

    Raises:
        CheckpointError: missing, corrupt or non-task checkpoint, a config or domain it lacks, or weights
            that do not fit the network its config describes (one-line message).
    """
    path, device = Path(path), torch.device(device)
    data = load_checkpoint(path, kind="task", map_location=device)
    try:
        cfg = Config.from_dict(data["config"])
        spec = env_spec(data["domain"])
    except (KeyError, TypeError) as err:
        raise CheckpointError(f"{path} lacks a usable config or domain ({err})") from None
    except (ConfigError, ValueError) as err:
        raise CheckpointError(f"{path}: {err}") from None
    with seeded_torch_rng(0, device):
        world_model = build_world_model(cfg, spec, device)
    try:
        world_model.load_state_dict(data["world_model"], strict=True)
    except (KeyError, RuntimeError) as err:
        # torch's message spans many lines (one per tensor); the first names the problem.
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(f"{path}: world model does not match its config ({first})") from None
    return TaskCheckpoint(path=path, data=data, config=cfg, spec=spec, world_model=world_model)
