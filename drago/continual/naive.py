"""The two reference points of every continual study: naive fine-tuning and training from scratch."""

from __future__ import annotations

from drago.continual.base import ContinualMethod


class Continual(ContinualMethod):
    """Continual TD-MPC (spec §5): world model carried over, trained on the task reward only."""


class Scratch(ContinualMethod):
    """TD-MPC from scratch: a fresh world model at every task, so nothing transfers or is retained."""

    name = "scratch"
    description = "TD-MPC from scratch: a fresh world model at every task"
    fresh_world_model = True
