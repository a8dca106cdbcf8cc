"""The two reference points of every continual study: naive fine-tuning and training from scratch."""

from __future__ import annotations

from drago.continual.base import ContinualMethod


class Continual(ContinualMethod):
    """Continual TD-MPC (paper §4): world model carried over, trained on the task reward only."""


class Scratch(ContinualMethod):
    """TD-MPC from scratch: a fresh world model at every task, so nothing transfers or is retained."""

    name = "scratch"
    description = "TD-MPC from scratch: a fresh world model at every task"
    fresh_world_model = True


class LearnerOnly(ContinualMethod):
    """Any method reduced to its plain learner: a test task with ``transfer.learner_only`` (paper §4.4).

    The reviewer, rehearsal, VAE updates, penalties and bonuses of the run's method are off; only its
    choice of a carried or fresh world model is kept (so a ``scratch`` run still learns from scratch).
    The authors ran their transfer baselines this way (``use_reviewer=false use_vae=false update_vae=false``).
    """

    name = "learner-only"
    description = "the run's method without its extras: only the learner, on the carried world model"

    def __init__(self, cfg, spec, device, fresh_world_model: bool = False):
        super().__init__(cfg, spec, device)
        self.fresh_world_model = fresh_world_model
