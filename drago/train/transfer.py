"""Transfer: a test task learned from the world model a run saved after stage K (spec §4.2-4.3).

A transfer is an ordinary single-task run whose config says where its world model comes from
(:class:`~drago.config.TransferConfig`): the trainer loads the stage-K checkpoint exactly as the next
task of the sequence would (world model, and the method's carried state such as DRAGO's VAE and
threshold), builds fresh heads, and trains for a fixed number of learner episodes, evaluating after
each one. Because it is a run directory like any other, ``drago resume DIR`` continues it after a crash
and a fixed seed gives the same logs.

The transfer's config is the source run's with these changes:

* ``env.tasks`` is the one test task, with the task catalogue's reward (test tasks sparse, training
  tasks dense) unless asked otherwise;
* ``agent.seed_steps=0``: no random seed phase, as in the authors' logged transfer run; actions are
  still random until the buffer holds one batch;
* separate budgets (``train.learner_steps_per_task``) of ``episodes`` learner episodes; DRAGO's reviewer
  may collect as many steps again, so it keeps its one reviewer episode per learner episode;
* ``train.eval_every_episodes``: evaluation after every learner episode (or every ``eval_every``).

The same function relearns a training task from a later world model (``--task room1 --after 4``), the
paper's walker appendix table for any domain.
"""

from __future__ import annotations

import copy
import csv
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from drago.config import Config, ConfigError, validate
from drago.train.run import CONFIG_FILE, RunDirError, new_run, read_run_config, resume
from drago.train.trainer import Trainer

__all__ = ["DEFAULT_EPISODES", "PAPER_CASES", "TransferCase", "default_transfer_dir", "describe", "finished_stages",
           "new_transfer", "paper_cases", "run_paper_cases", "run_transfer", "stage_checkpoint", "transfer_config",
           "transfer_summary"]

DEFAULT_EPISODES = 20  # learner episodes of a transfer (the few-shot protocol, spec §4.3)
TRANSFER_FOLDER = "transfer"

TransferCase = tuple[str, int]  # (test task, stage K)

#: The paper's test tasks per domain and the stage each is learned after (spec §1.1.4).
PAPER_CASES: dict[str, tuple[TransferCase, ...]] = {
    "minigrid": (("room1to2", 2), ("room1to3", 3), ("room1to3", 4), ("room3to4", 4)),
}


def default_transfer_dir(run_dir: Path, task: str, after: int) -> Path:
    return Path(run_dir) / TRANSFER_FOLDER / f"{task}-after{after}"


def paper_cases(domain: str) -> tuple[TransferCase, ...]:
    if domain not in PAPER_CASES:
        raise RunDirError(f"the paper has no transfer cases for domain '{domain}'; "
                          f"domains with cases: {', '.join(PAPER_CASES)}")
    return PAPER_CASES[domain]


def stage_checkpoint(run_dir: Path, cfg: Config, after: int) -> Path:
    """The task checkpoint a run wrote after its ``after``-th task (1-based)."""
    return Path(run_dir) / "checkpoints" / f"task{after}_{cfg.env.tasks[after - 1]}.pt"


def finished_stages(run_dir: Path, cfg: Config) -> list[int]:
    """Stages K (1-based) whose task checkpoint exists."""
    return [k for k in range(1, len(cfg.env.tasks) + 1) if stage_checkpoint(run_dir, cfg, k).is_file()]


def _check_task(source: Config, task: str) -> None:
    from drago.envs import available_tasks

    valid = available_tasks(source.env.domain)
    if task not in valid:
        raise ConfigError(f"unknown task '{task}' for domain {source.env.domain}; valid tasks: {', '.join(valid)}")


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


def transfer_config(source: Config, task: str, checkpoint: str, after: int, episodes: int = DEFAULT_EPISODES,
                    learner_only: bool = False, few_shot_episodes: int | None = None, eval_every: int = 1,
                    dense_reward: bool | None = None) -> Config:
    """The config of a transfer run, derived from its source run's config (see the module docstring).

    Args:
        source: the source run's config.
        task: the task to learn (any task of the source's domain).
        checkpoint: the stage checkpoint, relative to the transfer run's directory (or absolute).
        after: the stage K that checkpoint ends.
        episodes: learner episodes to train.
        learner_only: turn the method's extras (DRAGO's reviewer and rehearsal) off.
        few_shot_episodes: learner episodes after which the few-shot score is read (None: 20, or
            ``episodes`` if fewer).
        eval_every: evaluate after every this many learner episodes.
        dense_reward: None for the catalogue's reward type of ``task``.

    Raises:
        ConfigError: one line naming the bad value.
    """
    _check_task(source, task)
    if few_shot_episodes is None:
        few_shot_episodes = min(DEFAULT_EPISODES, episodes)
    for name, value in (("--episodes", episodes), ("--few-shot-episodes", few_shot_episodes),
                        ("--eval-every", eval_every)):
        if value <= 0:
            raise ConfigError(f"{name} must be a positive integer, got {value}")
    if few_shot_episodes % eval_every:
        raise ConfigError(f"--few-shot-episodes ({few_shot_episodes}) must be a multiple of --eval-every "
                          f"({eval_every}), so that an evaluation falls on it")
    cfg = copy.deepcopy(source)
    steps = episodes * cfg.env.episode_length
    cfg.env.tasks = (task,)
    cfg.env.dense_reward = dense_reward
    cfg.agent.seed_steps = 0
    cfg.train.learner_steps_per_task = steps
    cfg.train.reviewer_steps_per_task = steps
    cfg.train.eval_every_episodes = eval_every
    cfg.transfer.checkpoint = checkpoint
    cfg.transfer.after = after
    cfg.transfer.learner_only = learner_only
    cfg.transfer.few_shot_episodes = few_shot_episodes
    validate(cfg)
    return cfg


def _planned(run_dir: Path, task: str, after: int, out: Path | None, **options: Any) -> tuple[Config, Path]:
    source = read_run_config(Path(run_dir))
    _check_task(source, task)  # before the stage check: a typo in the task is the likelier mistake
    checkpoint = _check_stage(Path(run_dir), source, after)
    out = Path(out) if out is not None else default_transfer_dir(run_dir, task, after)
    # Relative to the transfer directory, so moving the whole run tree keeps the link.
    relative = os.path.relpath(checkpoint.resolve(), out.resolve())
    return transfer_config(source, task, relative, after, **options), out


def new_transfer(run_dir: Path, task: str, after: int, out: Path | None = None, force: bool = False,
                 progress: bool = True, **options: Any) -> Trainer:
    """Create the transfer run directory and return its trainer (call ``.run()`` to train).

    ``options`` are :func:`transfer_config`'s keyword arguments. The directory defaults to
    ``RUN_DIR/transfer/{task}-after{K}``; an existing one is refused unless ``force``.

    Raises:
        RunDirError, ConfigError: one line (unknown task, stage out of range or not finished yet, not a
            run directory, existing transfer directory, bad option).
    """
    cfg, out = _planned(run_dir, task, after, out, **options)
    return new_run(cfg, out, force=force, progress=progress)


def run_transfer(trainer: Trainer) -> dict[str, Any]:
    """Train a transfer run built by :func:`new_transfer` (or resumed) and print its few-shot scores."""
    summary = trainer.run()
    trainer.logger.print(describe(summary))
    trainer.logger.close()
    return summary


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
    return (f"[{t['task']} after {t['after']}] few-shot return after {t['few_shot_episodes']} learner episodes: "
            f"{score(few['equal_episodes'])}; at equal env steps: {score(few['equal_env_steps'])}")


def run_paper_cases(run_dir: Path, out: Path | None = None, force: bool = False, progress: bool = True,
                    **options: Any) -> list[dict[str, Any]]:
    """Run the paper's transfer cases of the run's domain one after the other.

    A case whose directory already holds a finished transfer with the same settings is skipped, an
    unfinished one is resumed; ``force`` redoes every case. ``out`` is the folder holding the cases
    (default ``RUN_DIR/transfer``). Every case is checked before the first one starts.

    Returns:
        The summary of each case, in order.
    """
    run_dir = Path(run_dir)
    source = read_run_config(run_dir)
    cases = paper_cases(source.env.domain)
    plans = []
    for task, after in cases:
        case_out = (Path(out) / f"{task}-after{after}") if out is not None else None
        cfg, case_dir = _planned(run_dir, task, after, case_out, **options)
        if case_dir.exists() and any(case_dir.iterdir()) and not force:
            _check_same_settings(case_dir, cfg)
        plans.append((task, after, cfg, case_dir))
    summaries = []
    for task, after, cfg, case_dir in plans:
        fresh = force or not (case_dir / CONFIG_FILE).is_file()
        trainer = new_run(cfg, case_dir, force=force, progress=progress) if fresh else resume(case_dir, progress)
        label = f"{task} after {after}"
        if trainer.completed_tasks() == len(cfg.env.tasks):
            summary = trainer.write_summary()
            trainer.logger.print(f"[{label}] already finished in {case_dir}; skipped. " + describe(summary))
            trainer.logger.close()
            summaries.append(summary)
            continue
        trainer.logger.print(f"[{label}] {'starting' if fresh else 'resuming'} -> {case_dir}")
        summaries.append(run_transfer(trainer))
    return summaries


def _check_same_settings(case_dir: Path, cfg: Config) -> None:
    if not (case_dir / CONFIG_FILE).is_file():
        raise RunDirError(f"{case_dir} is not empty and not a drago run; move it away or pass --force")
    existing = read_run_config(case_dir).to_dict()
    wanted = cfg.to_dict()
    diffs = [f"{section}.{key}: {existing[section].get(key)!r} there, {value!r} asked"
             for section, values in wanted.items() if isinstance(values, dict)
             for key, value in values.items() if existing[section].get(key) != value]
    if diffs:
        raise RunDirError(f"{case_dir} holds a transfer with other settings ({'; '.join(diffs[:3])}); "
                          "pass --force to redo it")


# ---- summary ---------------------------------------------------------------------------------------
def _eval_point(row: dict[str, str]) -> dict[str, Any]:
    def number(key: str) -> float | None:
        return float(row[key]) if row.get(key) not in (None, "") else None

    return {"episode": int(row["episode"]), "learner_env_steps": int(row["learner_env_step"]),
            "total_env_steps": int(row["env_step"]), "return": number("episode_reward"),
            "return_std": number("episode_reward_std"), "fraction_of_optimal": number("fraction_of_optimal")}


def transfer_summary(cfg: Config, run_dir: Path, tasks: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The transfer block of ``summary.json``: few-shot scores and the budget actually spent.

    The few-shot score is read twice (spec §4.3 leaves the comparison open): after
    ``few_shot_episodes`` learner episodes (``equal_episodes``, the paper's reading for DRAGO), and at the
    last evaluation whose total env steps (learner plus reviewer) do not exceed what a learner alone
    spends in that many episodes (``equal_env_steps``). Without a reviewer the two coincide. A score is
    None until the run has reached it.
    """
    from drago.envs import GRID_TASKS, task_optimum
    from drago.envs.tasks import get_grid_task

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
    if cfg.env.domain == "minigrid" and task in GRID_TASKS:
        dense = get_grid_task(task, dense).dense
    done = tasks[0] if tasks else None
    planned = (cfg.train.learner_steps_per_task or 0) // cfg.env.episode_length
    return {
        "task": task, "after": cfg.transfer.after, "source_checkpoint": cfg.transfer.checkpoint,
        "method": cfg.method.name, "learner_only": cfg.transfer.learner_only,
        "reward": None if dense is None else ("dense" if dense else "sparse"),
        "optimal_return": task_optimum(cfg.env.domain, task, cfg.env.dense_reward),
        "episodes_planned": planned, "few_shot_episodes": few,
        "few_shot": {"equal_episodes": at_episodes, "equal_env_steps": at_env_steps},
        "final": points[-1] if done and points else None,
        "learner_env_steps": done["learner_steps"] * cfg.env.action_repeat if done else None,
        "total_env_steps": done["env_steps"] if done else None,
        "wall_time_s": done["wall_time_s"] if done else None,
    }
