"""The continual-method interface: a small strategy object with named hooks.

The trainer owns the loop (collect, update, evaluate, checkpoint) and calls these hooks; a method
changes only what differs. A new method is a subclass registered under a name
(:func:`drago.continual.registry.register_method`; docs: Extending drago).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from drago.agent.protocol import ContinualAgent
from drago.agent.buffer import EpisodeReplay
from drago.agent.factory import replay_horizon
from drago.config import Config, MethodSetting
from drago.envs import EnvSpec


MAX_BUFFER = 1_000_000  # transitions, as in the official code


def buffer_capacity(steps: int, episode_length: int) -> int:
    """Room for ``steps`` transitions in whole episodes, so no episode of a task is overwritten."""
    return -(-min(steps, MAX_BUFFER) // episode_length) * episode_length


def task_replay(cfg: Config, spec: EnvSpec, steps: int, device: torch.device | str) -> EpisodeReplay:
    """The prioritized replay of one agent's episodes of a task (at most ``steps`` transitions), in the
    sequences its agent kind learns from: the learner's, and DRAGO's reviewer's."""
    return EpisodeReplay(buffer_capacity(steps, cfg.env.episode_length), spec.obs_dim, spec.action_dim,
                         replay_horizon(cfg), cfg.env.episode_length, cfg.agent.per_alpha, cfg.agent.per_beta,
                         device=device)


@dataclass(frozen=True)
class Budget:
    """How many agent steps a task may take (docs: Design, paper and code: budgets).

    Shared (the official code's accounting, the default): learner and reviewer steps count together
    against ``steps_per_task``, so once a reviewer runs the learner gets half the steps. Separate (either of
    ``learner_steps_per_task`` and ``reviewer_steps_per_task`` set): the task ends after ``learner`` learner
    steps (``steps_per_task`` unless set) and the reviewer collects up to ``reviewer`` steps (as many unless set).
    """

    shared: int | None
    learner: int | None = None
    reviewer: int | None = None

    @classmethod
    def from_config(cls, cfg: Config) -> Budget:
        t = cfg.train
        if t.learner_steps_per_task is None and t.reviewer_steps_per_task is None:
            return cls(shared=t.steps_per_task)
        learner = t.learner_steps_per_task if t.learner_steps_per_task is not None else t.steps_per_task
        reviewer = t.reviewer_steps_per_task if t.reviewer_steps_per_task is not None else learner
        return cls(shared=None, learner=learner, reviewer=reviewer)

    @property
    def max_steps(self) -> int:
        """An upper bound on a task's agent steps (progress bars, global log steps)."""
        return self.shared if self.shared is not None else self.learner + self.reviewer

    @property
    def max_learner_steps(self) -> int:
        return self.shared if self.shared is not None else self.learner

    @property
    def max_reviewer_steps(self) -> int:
        # Shared: one reviewer episode per learner episode, so at most half of the task, rounded up.
        return -(-self.shared // 2) if self.shared is not None else self.reviewer

    def describe(self) -> str:
        """One line for a study's plan: who gets how many agent steps a task, and the setting for the other way."""
        if self.shared is not None:
            return (f"{self.shared:,} agent steps a task, learner and reviewer together (the official code's "
                    "accounting: once DRAGO's reviewer runs, its learner gets half); separate budgets: "
                    "train.learner_steps_per_task=N and/or train.reviewer_steps_per_task=M")
        return (f"{self.learner:,} learner steps a task for every method, up to {self.reviewer:,} more for DRAGO's "
                "reviewer; the official code's shared accounting: train.learner_steps_per_task=null "
                "train.reviewer_steps_per_task=null")

    def finished(self, task: TaskState) -> bool:
        if self.shared is not None:
            return task.step >= self.shared
        return task.learner_steps >= self.learner

    def reviewer_may_collect(self, task: TaskState) -> bool:
        return self.shared is not None or task.step - task.learner_steps < self.reviewer


@dataclass
class TaskState:
    """Everything that lives for one task of the sequence (paper §3.3; docs: Design, how a run flows: fresh at every task).

    The world model is the exception: the method decides whether it arrives fresh or carried over.
    """

    index: int
    name: str
    world_model: torch.nn.Module
    world_optimizer: torch.optim.Optimizer
    learner: ContinualAgent
    buffer: EpisodeReplay
    rng: np.random.Generator
    env: Any  # the task's env, shared by every episode of the task (as in the official code)
    budget: Budget
    step: int = 0  # task-local agent steps, learner and reviewer together
    learner_steps: int = 0
    episodes: int = 0
    extras: dict[str, Any] = field(default_factory=dict)  # a method's per-task objects (DRAGO's reviewer, ...)
    schedule_clock: str = "task"  # agent.schedule_clock

    @property
    def schedule_step(self) -> int:
        """Where the agents' schedules stand (``agent.schedule_clock``): the task's agent steps, or the learner's."""
        return self.learner_steps if self.schedule_clock == "learner" else self.step


class ContinualMethod:
    """Naive continual TD-MPC: the world model is carried over and fine-tuned on each new task.

    Subclasses override hooks; every default here is the plain TD-MPC behaviour.
    """

    name = "continual"
    description = "continual TD-MPC: carry the world model over and fine-tune it on each task"
    #: Build a fresh world model at every task instead of carrying the previous one over.
    fresh_world_model = False
    #: Whether another agent (DRAGO's reviewer) plays episodes of a task besides the learner: only then do a
    #: task's steps and its learner's differ, so only then does ``agent.schedule_clock`` change anything.
    second_agent = False
    #: Settings of the method's own, by name (a plug-in cannot add fields to drago's config): each is set as
    #: ``method.NAME=value`` and read with :meth:`setting` (docs: Extending drago, "Settings of your own").
    settings: dict[str, MethodSetting] = {}
    #: The sections of ``method`` the method reads (``vae``, ``ewc``, ...): a setting of another section named
    #: on the command line is an error, and the others are left out of a record's protocol.
    reads: tuple[str, ...] = ()

    def __init__(self, cfg: Config, spec: EnvSpec, device: torch.device):
        self.cfg = cfg
        self.spec = spec
        self.device = device

    @classmethod
    def config_problem(cls, cfg: Config) -> str | None:
        """Why this method cannot run with ``cfg`` (completing "method 'NAME' ..."), or None when it can.

        Checked when the config is loaded, so a method that needs what the agent lacks (TD-MPC's value heads
        on ``agent.kind=pets``) says so in one line before anything runs. The hooks' defaults serve both
        agent kinds.
        """
        return None

    def setting(self, name: str) -> Any:
        """The value of one of the method's own :attr:`settings`: the config's, else its default."""
        return self.cfg.method.options.get(name, self.settings[name].default)

    # ---- task boundaries -------------------------------------------------------------------
    def begin_task(self, task: TaskState) -> None:
        """Called once the task's world model, learner and buffer exist, before any step."""

    def end_task(self, task: TaskState) -> None:
        """Called after the task's last update and final evaluation, before its checkpoint."""

    # ---- inside an iteration ---------------------------------------------------------------
    def collect(self, task: TaskState) -> dict[str, float]:
        """Extra data collection after each learner episode (DRAGO's reviewer); returns log values."""
        return {}

    def collected_buffers(self, task: TaskState) -> dict[str, EpisodeReplay]:
        """This task's episodes that :meth:`collect` gathered, by the agent that played them (DRAGO: its
        reviewer's buffer), for records such as where each agent went; the learner's are ``task.buffer``."""
        return {}

    def gradient_step(self, task: TaskState, u: int) -> dict[str, torch.Tensor]:
        """One gradient iteration u: by default a learner update that also trains the world model."""
        batch = task.buffer.sample(self.cfg.agent.batch_size, task.rng)
        metrics = task.learner.update(batch, u, train_world_model=True, world_model_loss=self.world_model_loss(task),
                                      **self.update_options(task))
        task.buffer.update_priorities(batch.indices, metrics.pop("priority"))
        return {f"learner_{k}": v for k, v in metrics.items()}

    def update_options(self, task: TaskState) -> dict[str, Any]:
        """Options of the learner's update that a capability of its agent adds (the curiosity baseline's bonus)."""
        return {}

    def world_model_loss(self, task: TaskState) -> Callable[[], torch.Tensor] | None:
        """An extra loss on the world model for this gradient step (EWC penalty, replayed old rows)."""
        return None

    # ---- persistence -----------------------------------------------------------------------
    def carry_state(self) -> dict[str, Any]:
        """What the next task inherits besides the world model (VAE, threshold, Fisher, ...)."""
        return {}

    def load_carry_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`carry_state` from the previous task's checkpoint."""

    def task_state_dict(self, task: TaskState) -> dict[str, Any]:
        """Mid-task state beyond the learner and its buffer, for a resumable checkpoint."""
        return {}

    def load_task_state_dict(self, task: TaskState, state: dict[str, Any]) -> None:
        """Restore :meth:`task_state_dict` when resuming in the middle of a task."""
