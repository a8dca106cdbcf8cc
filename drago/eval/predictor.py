"""A trained world model behind a numpy interface: what every evaluation and the public API predict with."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from drago.agent.networks import WorldModel
from drago.training.checkpoint import load_task_checkpoint

# Rows per forward pass: large enough to amortise Python overhead, small enough to bound memory.
PREDICT_CHUNK = 8192


class WorldModelPredictor:
    """A trained world model behind a numpy interface.

    Attributes:
        world_model: The torch :class:`~drago.agent.networks.WorldModel`, in eval mode.
        obs_dim: Observation width the model expects.
        action_dim: Action width the model expects (one-hot width on the grid).
        domain: Domain of the checkpoint, e.g. ``"minigrid"``.
        task: Name of the task whose end wrote the checkpoint, or None.
        task_index: Zero-based position of that task in the run's sequence, or None.
    """

    def __init__(self, world_model: WorldModel, domain: str, task: str | None = None,
                 task_index: int | None = None):
        self.world_model = world_model.eval()
        self.obs_dim = int(world_model.obs_dim)
        self.action_dim = int(world_model.action_dim)
        self.domain = domain
        self.task = task
        self.task_index = task_index

    @property
    def device(self) -> torch.device:
        return next(self.world_model.parameters()).device

    def predict(self, obs: Any, action: Any) -> np.ndarray:
        """Predicted next observations, exactly as the agent's planner sees them.

        The observation is encoded (identity unless an encoder is enabled) and passed with the action
        through the dynamics, clamp and squash of :meth:`WorldModel.forward`.

        Args:
            obs: Array-like of shape (N, obs_dim).
            action: Array-like of shape (N, action_dim); one-hot rows on the grid.

        Returns:
            float32 array of shape (N, obs_dim).

        Raises:
            ValueError: If the shapes do not match the model.
        """
        obs = np.asarray(obs, dtype=np.float32)
        action = np.asarray(action, dtype=np.float32)
        if (obs.ndim != 2 or action.ndim != 2 or obs.shape[1] != self.obs_dim
                or action.shape[1] != self.action_dim or obs.shape[0] != action.shape[0]):
            raise ValueError(f"predict expects obs of shape (N, {self.obs_dim}) and action of shape "
                             f"(N, {self.action_dim}) with the same N; got obs {obs.shape} and action {action.shape}")
        out = np.empty((obs.shape[0], self.obs_dim), dtype=np.float32)
        device = self.device
        with torch.inference_mode():
            for start in range(0, obs.shape[0], PREDICT_CHUNK):
                stop = start + PREDICT_CHUNK
                # torch.tensor copies, so read-only inputs (e.g. cached transitions) are fine.
                o = torch.tensor(obs[start:stop], device=device)
                a = torch.tensor(action[start:stop], device=device)
                out[start:stop] = self.world_model(self.world_model.encode(o), a).float().cpu().numpy()
        return out

    def __repr__(self) -> str:
        where = f", task={self.task!r} (index {self.task_index})" if self.task is not None else ""
        return (f"WorldModelPredictor(domain={self.domain!r}, obs_dim={self.obs_dim}, "
                f"action_dim={self.action_dim}{where})")


def load_world_model(checkpoint_path: str | Path, device: str = "cpu") -> WorldModelPredictor:
    """Load the world model of a task checkpoint (``checkpoints/task<k>_<name>.pt`` of a run).

    The network is rebuilt from the configuration stored in the checkpoint, so a run trained with
    any width or activation loads without further arguments, and the weights are loaded strictly.

    Args:
        checkpoint_path: Path of a task checkpoint.
        device: Torch device to put the model on, e.g. ``"cpu"`` or ``"cuda"``.

    Returns:
        A :class:`WorldModelPredictor` whose ``predict(obs, action)`` maps numpy batches to the
        predicted next observations.

    Raises:
        drago.training.checkpoint.CheckpointError: Missing, corrupt or non-task checkpoint, or weights
            that do not fit the network its configuration describes (one-line message).
    """
    loaded = load_task_checkpoint(checkpoint_path, device)
    return WorldModelPredictor(loaded.world_model, domain=loaded.data["domain"], task=loaded.task,
                               task_index=loaded.task_index)
