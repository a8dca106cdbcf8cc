"""What DRAGO's reviewer is paid, on every grid transition, when a task begins (paper §3.2; docs: Evaluation,
where the reviewer goes).

The reviewer of task k+1 plans for the intrinsic reward r = r_old − α·c, where r_old says how well the frozen
model of stage k predicts a transition and c how well the current model does. Both are compared with θ, the
moving average of the learner's prediction score that stage k's checkpoint saved. At the start of task k+1 the
current model *is* stage k's model, so the pay of every transition of the grid follows from one checkpoint:
:func:`reviewer_pay_of_run` evaluates :func:`~drago.continual.generative.intrinsic_reward`, the function the
reviewer is trained on, on all 6,732 transitions (:func:`~drago.eval.coverage.grid_transitions`).

This is the map a reviewer that regains old rooms must follow: if r_old is near zero on most of an old room,
no planner can be drawn back there by it, however long it trains.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from drago.config import INTRINSIC_REWARDS, ConfigError
from drago.continual.generative import intrinsic_reward
from drago.continual.registry import get_method
from drago.eval.coverage import ALL, GROUPS, transition_groups, grid_transitions, run_checkpoints
from drago.training.checkpoint import load_task_checkpoint

__all__ = ["PAID", "StagePay", "reviewer_pay_of_run"]

#: A transition "pays" when its old-model term is above this: the old model predicts it about as well as θ.
PAID = 0.5


@dataclass(frozen=True)
class StagePay:
    """The reviewer's pay on every grid transition at the start of the task after ``stage``.

    Attributes:
        stage: the stage whose world model is the old model (1-based).
        task: the task learned in that stage.
        next_task: the task whose reviewer is paid so.
        threshold: the θ the reviewer is paid against: the one saved by the stage's checkpoint, less the run's
            ``method.reviewer.threshold_offset``.
        old_term: (N,) r_old per transition of :func:`~drago.eval.coverage.grid_transitions`, in (0, 1).
        cost: (N,) c per transition (the current model is the old one when the task begins), in (0, 1).
        reward: (N,) r_old − α·c, what the reviewer plans for.
        rooms: per group of :data:`~drago.eval.coverage.GROUPS`: the mean ``old_term``, the share of
            transitions with ``old_term > PAID`` (``paid``) and the mean ``reward``.
    """

    stage: int
    task: str
    next_task: str
    threshold: float
    old_term: np.ndarray
    cost: np.ndarray
    reward: np.ndarray
    rooms: dict[str, dict[str, float]]


def pays_a_reviewer(method: str) -> bool:
    """Whether a method's runs plan for DRAGO's intrinsic reward (a reviewer, or a learner given it)."""
    try:
        return bool(getattr(get_method(method), "use_reviewer", False))
    except ConfigError:  # a plug-in that is not installed here: its runs are reported without this section
        return False


def reviewer_pay_of_run(run_dir: str | Path, device: str = "cpu", variant: str | None = None,
                        threshold: float | None = None) -> list[StagePay]:
    """The pay maps of every finished stage of a grid run that is followed by another task of its sequence.

    Returns an empty list for runs whose method pays no reviewer (``continual``, ``drago-no-reviewer``, ...).

    ``variant`` and ``threshold`` ask "what would this reviewer have been paid" on the same checkpoints: the
    other form of the reward (``paper`` or ``code``, see
    :func:`~drago.continual.generative.intrinsic_reward`) or another θ than the run's. By default the
    run's own form and θ (each checkpoint's, less ``method.reviewer.threshold_offset``): what its reviewer was paid.

    Raises:
        CoverageError: Not a grid run, or no task finished yet.
        drago.training.checkpoint.CheckpointError: A corrupt or mismatched checkpoint.
    """
    cfg, checkpoints = run_checkpoints(run_dir)
    if not pays_a_reviewer(cfg.method.name):
        return []
    variant = variant or cfg.method.reviewer.intrinsic_reward
    if variant not in INTRINSIC_REWARDS:
        raise ConfigError(f"unknown intrinsic reward variant '{variant}'; valid: {', '.join(INTRINSIC_REWARDS)}")
    data = grid_transitions()
    obs, actions, next_obs = (torch.tensor(a, device=device) for a in data[:3])  # copies: the arrays are read-only
    groups = transition_groups()
    pays = []
    for checkpoint in checkpoints:
        if checkpoint.stage >= len(cfg.env.tasks):
            continue
        loaded = load_task_checkpoint(checkpoint.path, device)
        if threshold is None:
            reviewer = cfg.method.reviewer
            theta = _saved_threshold(loaded.data, reviewer.initial_threshold) - reviewer.threshold_offset
        else:
            theta = threshold
        model = loaded.world_model.eval()
        pay = intrinsic_reward(model, model, obs, actions, next_obs, theta, cfg.method.reviewer.cost_coef, variant)
        old_term, cost, reward = (t.double().cpu().numpy() for t in (pay.old_reward, pay.cost, pay.reward))
        rooms = {}
        for group in GROUPS:
            mask = np.ones(len(groups), dtype=bool) if group == ALL else groups == group
            rooms[group] = {"old_term": float(old_term[mask].mean()), "paid": float((old_term[mask] > PAID).mean()),
                            "reward": float(reward[mask].mean())}
        pays.append(StagePay(checkpoint.stage, checkpoint.task, cfg.env.tasks[checkpoint.stage], theta,
                             old_term, cost, reward, rooms))
    return pays


def _saved_threshold(data: dict[str, Any], default: float) -> float:
    # The DRAGO family saves θ with the state it carries to the next task (Drago.carry_state).
    method_state = data.get("method") or {}
    return float(method_state.get("threshold", default))
