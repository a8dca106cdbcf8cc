"""Transfer: a test task learned from the world model a run saved after stage K (paper §4.4).

A transfer is an ordinary single-task run whose config says where its world model comes from
(:class:`~drago.config.TransferConfig`): the trainer loads the stage-K checkpoint exactly as the next
task of the sequence would (world model, and the method's carried state such as DRAGO's VAE and
threshold), builds fresh heads, and trains for a fixed number of learner episodes, evaluating after
each one. Because it is a run directory like any other, ``drago resume DIR`` continues it after a crash
and a fixed seed gives the same logs.

The transfer's config is the source run's with these changes:

* ``env.tasks`` is the one test task, with the task catalogue's reward (test tasks sparse, training
  tasks dense) unless asked otherwise, by the command or by the source run's ``transfer.reward``
  (the PETS presets: dense, as in paper Appendix E);
* ``agent.seed_steps=0``: no random seed phase, as in the authors' logged transfer run; actions are
  still random until the buffer holds one batch;
* separate budgets (``train.learner_steps_per_task``) of ``episodes`` learner episodes; DRAGO's reviewer
  may collect as many steps again, so it keeps its one reviewer episode per learner episode;
* ``train.eval_every_episodes``: evaluation after every learner episode (or every ``eval_every``).

The same function relearns a training task from a later world model (``--task room1 --after 4``), the
paper's walker appendix table for any domain.

DeepMind Control test tasks (paper §4.4, Table 1) are named by their catalogue entry
(:data:`~drago.envs.tasks.DMC_TRANSFER_TASKS`, e.g. ``--task jump2run --after 2``): the run learns the
entry's target task, and for the "X2Y" entries every learner and evaluation episode starts with a
pre-rollout (:class:`PreRollout`): a reset, then ``pre_rollout_steps`` agent steps of the source task's
learner as saved in that task's checkpoint of the same run (its heads and world model, eval-mode
planning). Those steps are neither stored nor counted; DRAGO's reviewer episodes start from a plain reset.
"""

from __future__ import annotations

import copy
import csv
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drago.config import Config, ConfigError, validate
from drago.envs import available_domains, available_tasks, get_domain, task_optimum
from drago.envs.tasks import DMC_TRANSFER_TASKS, DmcTransferTask
from drago.training.rundir import TRANSFER_FOLDER, RunDirError, read_run_config, task_checkpoint_path

__all__ = ["DEFAULT_EPISODES", "TransferCase", "default_transfer_dir", "describe",
           "few_shot_schedule", "finished_stages", "paper_cases", "paper_transfer_plan", "plan_transfer",
           "resolve_task", "reward_variant", "stage_checkpoint", "training_returns", "transfer_config",
           "transfer_summary"]

DEFAULT_EPISODES = 20  # learner episodes of a transfer (the few-shot protocol, paper §4.4)

TransferCase = tuple[str, int]  # (test task, stage K)



def default_transfer_dir(run_dir: Path, task: str, after: int, reward: str | None = None) -> Path:
    """``RUN_DIR/transfer/TASK-afterK``; ``TASK-REWARD-afterK`` for a transfer that asks for another reward than
    the run's transfers get by default (``reward``, from :func:`reward_variant`), so the two never share one."""
    return Path(run_dir) / TRANSFER_FOLDER / (f"{task}-{reward}-after{after}" if reward else f"{task}-after{after}")


def reward_variant(source: Config, task: str, dense_reward: bool | None) -> str | None:
    """``"dense"`` or ``"sparse"`` when a transfer of ``task`` from a run with config ``source`` asks for another
    reward than the run's transfers default to (its ``transfer.reward``, else the task's own); None otherwise,
    and always on DeepMind Control, whose tasks have one reward each."""
    task_default = get_domain(source.env.domain).dense_by_default.get(task)
    if dense_reward is None or task_default is None:
        return None
    default = source.transfer.reward == "dense" if source.transfer.reward is not None else task_default
    return None if dense_reward == default else ("dense" if dense_reward else "sparse")


def paper_cases(domain: str) -> tuple[TransferCase, ...]:
    """The domain's standard transfer cases (:attr:`~drago.envs.domain.Domain.transfer_cases`)."""
    cases = get_domain(domain).transfer_cases
    if not cases:
        with_cases = [name for name in available_domains() if get_domain(name).transfer_cases]
        raise RunDirError(f"domain '{domain}' declares no transfer cases; domains with cases: {', '.join(with_cases)}")
    return cases


def stage_checkpoint(run_dir: Path, cfg: Config, after: int) -> Path:
    """The task checkpoint a run wrote after its ``after``-th task (1-based)."""
    return task_checkpoint_path(run_dir, cfg.env.tasks, after)


def finished_stages(run_dir: Path, cfg: Config) -> list[int]:
    """Stages K (1-based) whose task checkpoint exists."""
    return [k for k in range(1, len(cfg.env.tasks) + 1) if stage_checkpoint(run_dir, cfg, k).is_file()]


def resolve_task(source: Config, task: str) -> tuple[str, DmcTransferTask | None]:
    """The task a transfer learns and its catalogue test task: a DeepMind Control test-task name
    (``jump2run``) gives its target task, any task of the domain stands for itself.

    Raises:
        ConfigError: a name that is neither (one line listing the valid ones).
    """
    domain = source.env.domain
    case = DMC_TRANSFER_TASKS.get(task)
    if case is not None and case.domain == domain:
        return case.target, case
    valid = available_tasks(domain)
    if task not in valid:
        cases = [name for name, c in DMC_TRANSFER_TASKS.items() if c.domain == domain]
        more = f"; test tasks: {', '.join(cases)}" if cases else ""
        raise ConfigError(f"unknown task '{task}' for domain {domain}; valid tasks: {', '.join(valid)}{more}")
    return task, None


def _check_stage(run_dir: Path, cfg: Config, after: int) -> Path:
    n = len(cfg.env.tasks)
    done = finished_stages(run_dir, cfg)
    have = f"finished stages: {', '.join(map(str, done))}" if done else "no stage is finished yet"
    if not 1 <= after <= n:
        raise RunDirError(f"--after {after} is out of range: {run_dir} has {n} tasks "
                          f"({', '.join(cfg.env.tasks)}); {have}")
    path = stage_checkpoint(run_dir, cfg, after)
    if not path.is_file():
        raise RunDirError(f"{run_dir} has no checkpoint after stage {after} ({path.name}); {have}")
    return path


def few_shot_schedule(episodes: int, few_shot_episodes: int | None = None, eval_every: int = 1,
                      flag: str = "--") -> int:
    """The learner episode the few-shot score is read after (None: 20, or ``episodes`` if fewer), checked
    against the episode budget and the evaluation period: an evaluation must fall on it.

    Args:
        flag: prefix of the option names in the error (``--transfer-`` for ``drago study``).

    Raises:
        ConfigError: one line naming the bad value.
    """
    if few_shot_episodes is None:
        few_shot_episodes = min(DEFAULT_EPISODES, episodes)
    for name, value in (("episodes", episodes), ("few-shot-episodes", few_shot_episodes),
                        ("eval-every", eval_every)):
        if value <= 0:
            raise ConfigError(f"{flag}{name} must be a positive integer, got {value}")
    if few_shot_episodes % eval_every:
        raise ConfigError(f"{flag}eval-every {eval_every} does not divide the {few_shot_episodes} few-shot "
                          f"episodes, so no evaluation would fall on them; choose a divisor of {few_shot_episodes}")
    return few_shot_episodes


def transfer_config(source: Config, task: str, checkpoint: str, after: int, episodes: int = DEFAULT_EPISODES,
                    learner_only: bool = False, few_shot_episodes: int | None = None, eval_every: int = 1,
                    dense_reward: bool | None = None, pre_rollout_checkpoint: str | None = None,
                    pre_rollout_steps: int | None = None, pre_rollout_planning: str = "source") -> Config:
    """The config of a transfer run, derived from its source run's config (see the module docstring).

    Args:
        source: the source run's config.
        task: the task to learn (any task of the source's domain), or a DeepMind Control test task of
            the catalogue (``jump2run``), which learns its target task.
        checkpoint: the stage checkpoint, relative to the transfer run's directory (or absolute).
        after: the stage K that checkpoint ends.
        episodes: learner episodes to train.
        learner_only: turn the method's extras (DRAGO's reviewer and rehearsal) off.
        few_shot_episodes: learner episodes after which the few-shot score is read (None: 20, or
            ``episodes`` if fewer).
        eval_every: evaluate after every this many learner episodes.
        dense_reward: None for the source run's ``transfer.reward``, and when that is unset too the
            catalogue's reward type of ``task``.
        pre_rollout_checkpoint: task checkpoint of the learner that starts every learner and evaluation
            episode (relative to the transfer run's directory, or absolute); required by the X2Y test tasks.
        pre_rollout_steps: agent steps of that pre-rollout (None: the test task's, 100).
        pre_rollout_planning: see ``transfer.pre_rollout_planning``.

    Raises:
        ConfigError: one line naming the bad value.
    """
    target, case = resolve_task(source, task)
    if case is not None and case.pre_rollout_source is not None and pre_rollout_checkpoint is None:
        raise ConfigError(f"test task {case.name} starts every episode after a pre-rollout of the "
                          f"{case.pre_rollout_source} learner: pass that task's checkpoint")
    if pre_rollout_steps is None:
        pre_rollout_steps = case.pre_rollout_steps if case is not None else 100
    few_shot_episodes = few_shot_schedule(episodes, few_shot_episodes, eval_every)
    cfg = copy.deepcopy(source)
    steps = episodes * cfg.env.episode_length
    cfg.env.tasks = (target,)
    if dense_reward is None and source.transfer.reward is not None:
        dense_reward = source.transfer.reward == "dense"
    cfg.env.dense_reward = dense_reward
    cfg.agent.seed_steps = 0
    cfg.train.learner_steps_per_task = steps
    cfg.train.reviewer_steps_per_task = steps
    cfg.train.eval_every_episodes = eval_every
    cfg.transfer.checkpoint = checkpoint
    cfg.transfer.after = after
    cfg.transfer.learner_only = learner_only
    cfg.transfer.few_shot_episodes = few_shot_episodes
    cfg.transfer.case = case.name if case is not None else None
    cfg.transfer.pre_rollout_checkpoint = pre_rollout_checkpoint
    cfg.transfer.pre_rollout_steps = pre_rollout_steps
    cfg.transfer.pre_rollout_planning = pre_rollout_planning
    if get_domain(cfg.env.domain).exact_world is None:  # an exact world records none anyway: its configs stay
        cfg.train.heldout_episodes = 0  # held-out sets measure a continual sequence's retention, not a transfer
    validate(cfg)
    return cfg


def _pre_rollout_stage(run_dir: Path, cfg: Config, case: DmcTransferTask) -> Path:
    """The checkpoint of the run's learner of ``case.pre_rollout_source`` (its last stage on that task)."""
    source_task = case.pre_rollout_source
    stages = [k for k, name in enumerate(cfg.env.tasks, start=1) if name == source_task]
    if not stages:
        raise RunDirError(f"{case.name} starts its episodes with the {source_task} learner, but {run_dir} never "
                          f"trains {source_task} (tasks: {', '.join(cfg.env.tasks)})")
    path = stage_checkpoint(run_dir, cfg, stages[-1])
    if not path.is_file():
        done = finished_stages(run_dir, cfg)
        have = f"finished stages: {', '.join(map(str, done))}" if done else "no stage is finished yet"
        raise RunDirError(f"{run_dir} has no checkpoint after stage {stages[-1]} ({path.name}), whose "
                          f"{source_task} learner {case.name} needs for its pre-rollouts; {have}")
    return path


def plan_transfer(run_dir: Path, task: str, after: int, out: Path | None, **options: Any) -> tuple[Config, Path]:
    """The config and directory of a transfer of ``task`` from ``run_dir``'s stage ``after``, all checked.

    ``options`` are :func:`transfer_config`'s keyword arguments.
    """
    source = read_run_config(Path(run_dir))
    _, case = resolve_task(source, task)  # before the stage check: a typo in the task is the likelier mistake
    checkpoint = _check_stage(Path(run_dir), source, after)
    out = (Path(out) if out is not None else
           default_transfer_dir(run_dir, task, after, reward_variant(source, task, options.get("dense_reward"))))
    # Relative to the transfer directory, so moving the whole run tree keeps the link.
    relative = os.path.relpath(checkpoint.resolve(), out.resolve())
    if case is not None and case.pre_rollout_source is not None:
        pre = _pre_rollout_stage(Path(run_dir), source, case)
        options = {**options, "pre_rollout_checkpoint": os.path.relpath(pre.resolve(), out.resolve())}
    return transfer_config(source, task, relative, after, **options), out


def describe(summary: dict[str, Any]) -> str:
    """One line with a transfer's few-shot scores, for the console."""
    t = summary["transfer"]

    def score(point: dict[str, Any] | None) -> str:
        if point is None:
            return "not reached"
        frac = point.get("fraction_of_optimal")
        return (f"{point['return']:.1f}" + (f" ({frac:.0%} of optimal)" if frac is not None else "")
                + f" at episode {point['episode']}, {point['total_env_steps']} env steps")

    few = t["few_shot"]
    name = f"{t['case']}: {t['task']}" if t.get("case") else t["task"]
    return (f"[{name} after {t['after']}] few-shot return after {t['few_shot_episodes']} learner episodes: "
            f"{score(few['equal_episodes'])}; at equal env steps: {score(few['equal_env_steps'])}")


def paper_transfer_plan(run_dir: Path, out: Path | None = None,
                        **options: Any) -> list[tuple[str, int, Config, Path]]:
    """``(task, stage, config, directory)`` of each of the paper's transfer cases of a run, all checked.

    ``out`` is the folder holding the cases (default ``RUN_DIR/transfer``).
    """
    run_dir = Path(run_dir)
    source = read_run_config(run_dir)
    # A catalogued test task is learned after a task found by name, so other sequences get its stage too.
    cases = tuple((task, after if catalogued is None else _paper_stage(run_dir, source, catalogued))
                  for task, after in paper_cases(source.env.domain)
                  for catalogued in [resolve_task(source, task)[1]])
    plans = []
    for task, after in cases:
        case_out = (Path(out) / f"{task}-after{after}") if out is not None else None
        cfg, case_dir = plan_transfer(run_dir, task, after, case_out, **options)
        plans.append((task, after, cfg, case_dir))
    return plans


def _paper_stage(run_dir: Path, cfg: Config, case: DmcTransferTask) -> int:
    """The stage of the run after which a Table 1 test task is learned: after its ``after`` task, found by
    name, so runs of the paper's sequence get the catalogue's stage (paper §4.4, Table 1)."""
    stages = [k for k, name in enumerate(cfg.env.tasks, start=1) if name == case.after]
    if not stages:
        raise RunDirError(f"{case.name} ({case.paper_name}) is learned after {case.after}, which {run_dir} never "
                          f"trains (tasks: {', '.join(cfg.env.tasks)}); run it with --task {case.name} --after K")
    return stages[-1]


# ---- summary ---------------------------------------------------------------------------------------
def _eval_point(row: dict[str, str]) -> dict[str, Any]:
    def number(key: str) -> float | None:
        return float(row[key]) if row.get(key) not in (None, "") else None

    return {"episode": int(row["episode"]), "learner_env_steps": int(row["learner_env_step"]),
            "total_env_steps": int(row["env_step"]), "return": number("episode_reward"),
            "return_std": number("episode_reward_std"), "fraction_of_optimal": number("fraction_of_optimal")}


def training_returns(cfg: Config, run_dir: Path) -> dict[str, Any] | None:
    """The learner's own episode returns over the few-shot episodes, from ``train.csv``; None until it has
    played them all.

    These are exploring episodes, not evaluations. On a sparse-reward grid task they say whether the
    learner ever reached the goal, which it must before its planner can head there: an evaluation return of
    0 alone does not tell an agent that never found the goal from one that has not yet learned the way.
    """
    few = cfg.transfer.few_shot_episodes
    path = Path(run_dir) / "train.csv"
    if not path.is_file():
        return None
    with path.open(newline="") as handle:
        returns = [float(r["episode_reward"]) for r in csv.DictReader(handle)
                   if r.get("task") == cfg.env.tasks[0] and r.get("episode") and int(r["episode"]) <= few]
    if len(returns) < few:
        return None
    return {"episodes": few, "mean_return": float(np.mean(returns)),
            "positive_episodes": int(sum(r > 0 for r in returns))}


def transfer_summary(cfg: Config, run_dir: Path, tasks: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The transfer block of ``summary.json``: few-shot scores and the budget actually spent.

    The few-shot score is read twice (paper §4.4 leaves the comparison open): after
    ``few_shot_episodes`` learner episodes (``equal_episodes``, the paper's reading for DRAGO), and at the
    last evaluation whose total env steps (learner plus reviewer) do not exceed what a learner alone
    spends in that many episodes (``equal_env_steps``). Without a reviewer the two coincide. A score is
    None until the run has reached it.
    """
    task = cfg.env.tasks[0]
    few = cfg.transfer.few_shot_episodes
    rows = []
    path = Path(run_dir) / "eval.csv"
    if path.is_file():
        with path.open(newline="") as handle:
            rows = [r for r in csv.DictReader(handle) if r.get("task") == task and r.get("episode")]
    points = [_eval_point(r) for r in rows]
    budget = few * cfg.env.episode_length * cfg.env.action_repeat
    at_episodes = next((p for p in points if p["episode"] == few), None)
    reached = [p for p in points if p["total_env_steps"] <= budget]
    # The last evaluation within the budget is final once the run has spent the whole budget.
    at_env_steps = reached[-1] if reached and points[-1]["total_env_steps"] >= budget else None
    dense = cfg.env.dense_reward
    if dense is None:
        dense = get_domain(cfg.env.domain).dense_by_default.get(task)
    done = tasks[0] if tasks else None
    planned = (cfg.train.learner_steps_per_task or 0) // cfg.env.episode_length
    pre_rollout = None
    if cfg.transfer.pre_rollout_checkpoint is not None:
        pre_rollout = {"checkpoint": cfg.transfer.pre_rollout_checkpoint, "steps": cfg.transfer.pre_rollout_steps,
                       "planning": cfg.transfer.pre_rollout_planning}
    return {
        "task": task, "case": cfg.transfer.case, "pre_rollout": pre_rollout,
        "after": cfg.transfer.after, "source_checkpoint": cfg.transfer.checkpoint,
        "method": cfg.method.name, "learner_only": cfg.transfer.learner_only,
        "reward": None if dense is None else ("dense" if dense else "sparse"),
        "optimal_return": task_optimum(cfg.env.domain, task, cfg.env.dense_reward),
        "episodes_planned": planned, "few_shot_episodes": few,
        "few_shot": {"equal_episodes": at_episodes, "equal_env_steps": at_env_steps},
        "training": training_returns(cfg, run_dir),
        "final": points[-1] if done and points else None,
        "learner_env_steps": done["learner_steps"] * cfg.env.action_repeat if done else None,
        "total_env_steps": done["env_steps"] if done else None,
        "wall_time_s": done["wall_time_s"] if done else None,
    }
