"""L2 anchor: continual TD-MPC with an L2 pull towards the previous task's world model.

A simpler relative of EWC: every weight is anchored with the same strength instead of its Fisher
information. Its strength is a setting of its own, ``method.anchor_coef`` (``drago train ... --method l2-anchor
method.anchor_coef=10``), declared in ``settings`` and read with ``self.setting``.
"""

from __future__ import annotations

from typing import Any

import torch

from drago.config import MethodSetting
from drago.continual import ContinualMethod


class L2Anchor(ContinualMethod):
    description = "continual TD-MPC with an L2 pull towards the previous task's world model (example plug-in)"
    settings = {"anchor_coef": MethodSetting(float, 100.0, "weight of the L2 pull towards the previous task's weights")}

    def __init__(self, cfg, spec, device):
        super().__init__(cfg, spec, device)
        self.anchor: dict[str, torch.Tensor] | None = None

    def world_model_loss(self, task):
        if self.anchor is None:
            return None
        params = dict(task.world_model.dynamics.named_parameters())
        anchor, coef = self.anchor, self.setting("anchor_coef")

        def penalty() -> torch.Tensor:
            return coef * sum(((params[k] - v) ** 2).sum() for k, v in anchor.items()) / 2

        return penalty

    def end_task(self, task) -> None:
        self.anchor = {k: p.detach().clone() for k, p in task.world_model.dynamics.named_parameters()}

    def carry_state(self) -> dict[str, Any]:
        return {"anchor": self.anchor} if self.anchor is not None else {}

    def load_carry_state(self, state: dict[str, Any]) -> None:
        anchor = state.get("anchor")
        self.anchor = {k: v.to(self.device) for k, v in anchor.items()} if anchor is not None else None
