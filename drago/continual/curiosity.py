"""Curiosity + continual TD-MPC (paper §4, the paper's appendix baseline).

The learner's TD target gets the bonus ``c * e_t``, with ``e_t`` the open-loop multi-step prediction
error of the current world model (paper §2; docs: Design, the agent), so the agent is drawn to transitions its carried-over
model predicts badly. As in the official code the bonus enters the TD target only: the reward head
still fits the environment reward, which is what the planner's reward predictions must be.
"""

from __future__ import annotations

from drago.agent.protocol import capabilities_of
from drago.continual.base import ContinualMethod


class Curiosity(ContinualMethod):
    """Continual TD-MPC whose critics value the world model's prediction error (``method.curiosity.coef``)."""

    name = "curiosity"
    reads = ("curiosity",)
    description = "continual TD-MPC with a prediction-error bonus c * e_t in the learner's TD target"

    def __init__(self, cfg, spec, device):
        super().__init__(cfg, spec, device)
        self.curiosity_coef = cfg.method.curiosity.coef

    def update_options(self, task):
        return {"curiosity_coef": self.curiosity_coef}

    @classmethod
    def config_problem(cls, cfg):
        if not capabilities_of(cfg.agent.kind).value_function:
            return (f"needs a learned value (its bonus enters the learner's TD target), which "
                    f"agent.kind={cfg.agent.kind} lacks; use agent.kind=tdmpc or another method")
        return None
