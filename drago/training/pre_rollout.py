"""The learner a task checkpoint holds, and the pre-rollouts that start the episodes of the DeepMind Control
"X2Y" test tasks (paper Table 1): a reset, then 100 agent steps of an earlier task's learner, so the test
task begins in states of that task."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from drago.agent.factory import build_agent
from drago.agent.protocol import ContinualAgent
from drago.config import Config
from drago.training.checkpoint import CheckpointError, load_task_checkpoint
from drago.seeding import seeded_torch_rng


@dataclass
class SavedLearner:
    """The learner a task checkpoint holds: its heads over that checkpoint's world model.

    Attributes:
        agent: planner-ready agent (never trained: it has no world-model optimizer).
        config: the config of the run that wrote the checkpoint.
        task: the checkpoint's task; task_index its 0-based position in that run's sequence.
        steps: the task's step counter at its end, where the learner's horizon schedule stood.
    """

    agent: ContinualAgent
    config: Config
    task: str
    task_index: int
    steps: int


def load_learner(path: str | Path, device: torch.device | str = "cpu") -> SavedLearner:
    """The final learner of a task checkpoint, planning as it did at the end of its task.

    Its CEM std floor is the one the trainer saved with it (checkpoints written before that field take
    the floor's schedule at the task's last step, the same up to one iteration's updates).

    Raises:
        drago.training.checkpoint.CheckpointError: missing, corrupt or foreign file, or no learner heads.
    """
    loaded = load_task_checkpoint(path, device)
    data, cfg = loaded.data, loaded.config
    if "learner" not in data:
        raise CheckpointError(f"{path} holds no learner heads; it cannot drive a pre-rollout or record held-out data")
    with seeded_torch_rng(0, device):  # the heads' initial weights, overwritten below
        agent = build_agent(cfg, loaded.spec, loaded.world_model, None, task=str(data["task"]))
    agent.load_task_state(data)
    steps = int(data["steps"])
    return SavedLearner(agent=agent, config=cfg, task=str(data["task"]), task_index=int(data["task_index"]),
                        steps=steps)


class PreRollout:
    """How an episode of an X2Y test task starts (paper §4.4, Table 1): reset, then ``steps`` agent steps of a
    saved learner in eval mode; returns the observation the test episode starts from.

    Nothing is stored or counted, and nothing is kept between episodes: the randomness of one
    pre-rollout comes from a seed drawn from the env's ``np_random`` right after the reset (the state a
    resumable checkpoint saves), on a torch stream of its own, so the trainer's streams do not move.

    Args:
        learner: the source learner (:func:`load_learner`).
        steps: agent steps of each pre-rollout.
        planning: ``"source"``: the horizon and CEM std floor the learner had at the end of its task;
            ``"code"``: the official code's quirk, the current task's horizon schedule and the initial
            std floor (paper §4.4, Table 1).
        device: where the learner lives.
    """

    def __init__(self, learner: SavedLearner, steps: int, planning: str = "source",
                 device: torch.device | str = "cpu"):
        self.learner = learner
        self.steps = int(steps)
        self.planning = planning
        self.device = torch.device(device)
        if planning == "code" and learner.agent.capabilities.plan_schedules:
            learner.agent.std_floor = learner.config.agent.tdmpc.std_schedule_start

    @classmethod
    def from_config(cls, cfg: Config, run_dir: Path, device: torch.device | str = "cpu") -> PreRollout:
        """The pre-rollout a run's ``transfer`` settings ask for (its checkpoint relative to ``run_dir``)."""
        path = Path(run_dir) / cfg.transfer.pre_rollout_checkpoint  # an absolute path stays absolute
        return cls(load_learner(path, device), cfg.transfer.pre_rollout_steps, cfg.transfer.pre_rollout_planning,
                   device)

    def __call__(self, env, task_step: int = 0) -> np.ndarray:
        """Reset ``env`` and pre-roll it; ``task_step`` is the current task's step ("code" planning)."""
        obs, _ = env.reset()
        if self.steps == 0:
            return obs
        agent = self.learner.agent
        plan_step = self.learner.steps if self.planning == "source" else task_step
        with seeded_torch_rng(int(env.np_random.integers(2**63)), self.device):
            for t in range(self.steps):
                obs, _, _, _, _ = env.step(agent.act(obs, plan_step, eval_mode=True, first_step=t == 0))
        return obs
