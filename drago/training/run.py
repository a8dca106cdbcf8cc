"""Start or continue runs and transfers: the composition root that hands the trainer what it calls."""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path
from typing import Any

import torch

from drago.agent.speed import resolve_speed, use_compile_cache
from drago.config import Config, ConfigError
from drago.continual import build_method
from drago.envs import env_spec
from drago.training.checkpoint import load_checkpoint
from drago.training.heldout_sets import HeldoutRecorder
from drago.training.logger import RunLogger
from drago.training.pre_rollout import PreRollout
from drago.training.resources import keep_freed_memory
from drago.training.rundir import (CONFIG_FILE, RunDirError, config_diffs, is_run_dir, read_run_config,
                                   resume_checkpoint_path, task_checkpoint_path, write_run_config)
from drago.training.tracking import check_tracking, wandb_tracker
from drago.training.trainer import Trainer, completed_tasks, global_env_step
from drago.training.visitation import VisitationRecorder
from drago.training.transfer import describe, paper_transfer_plan, plan_transfer, transfer_summary


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM during work that knows how it is continued (a run, a transfer, a study): the message
    says how, and ``drago`` prints it instead of the generic hint."""


@contextlib.contextmanager
def continue_with(how: str):
    """Inside, an interrupt becomes :class:`Interrupted` saying ``how`` to continue (an inner one's word stands)."""
    try:
        yield
    except Interrupted:
        raise
    except KeyboardInterrupt:
        raise Interrupted(how) from None


def default_run_dir(cfg: Config) -> Path:
    return Path("runs") / cfg.preset / cfg.method.name / f"seed{cfg.train.seed}"


def resolve_device(name: str) -> torch.device:
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device '{name}' was requested but CUDA is not available; use train.device=cpu")
    return torch.device(name)


def set_threads(threads: int) -> None:
    torch.set_num_threads(threads or os.cpu_count() or 1)


def _prepare_process(cfg: Config) -> None:
    """Process-wide settings of a run, applied before it touches its directory (a bad one fails first)."""
    check_tracking(cfg)
    set_threads(cfg.train.threads)
    keep_freed_memory()
    if cfg.agent.tdmpc.compile == "true":
        use_compile_cache()


def new_run(cfg: Config, run_dir: Path, force: bool = False, progress: bool = True) -> Trainer:
    """Create ``run_dir`` for ``cfg`` (refusing to overwrite a run unless ``force``) and build its trainer.

    The agent's ``auto`` speed settings are resolved here, for this machine, and written into the run's
    config.yaml; ``trainer.speed_notes`` says why an ``auto`` chose the slower path."""
    device = resolve_device(cfg.train.device)
    cfg, speed_notes = resolve_speed(cfg, device)
    _prepare_process(cfg)
    if run_dir.exists() and any(run_dir.iterdir()):
        if not force:
            raise RunDirError(f"run directory {run_dir} already exists; pass --force to overwrite it "
                              f"or `drago resume {run_dir}` to continue it")
        if not (run_dir / CONFIG_FILE).exists():
            raise RunDirError(f"{run_dir} is not empty and not a drago run; refusing to delete it, choose another --out")
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_run_config(run_dir, cfg)
    trainer = _build(cfg, run_dir, device, progress)
    trainer.speed_notes = speed_notes
    return trainer


def resume(run_dir: Path, progress: bool = True) -> Trainer:
    """Rebuild the trainer of an existing run; it continues where the last checkpoint left off."""
    cfg = read_run_config(run_dir)
    device = resolve_device(cfg.train.device)
    _prepare_process(cfg)
    done = completed_tasks(cfg, run_dir)
    # Read every finished task's checkpoint now, so a damaged one fails before any work starts.
    for index in range(done):
        load_checkpoint(task_checkpoint_path(run_dir, cfg.env.tasks, index + 1), kind="task", domain=cfg.env.domain)
    # TensorBoard must forget the events written after the checkpoint the run continues from. A checkpoint is
    # written after the rows of its own step, so those stay: the purge starts one step later.
    if resume_checkpoint_path(run_dir).exists():
        state = load_checkpoint(resume_checkpoint_path(run_dir), kind="resume", domain=cfg.env.domain)
        checkpointed = global_env_step(cfg, state["task_index"], state["step"])
    else:
        checkpointed = global_env_step(cfg, done)
    return _build(cfg, run_dir, device, progress, purge_step=checkpointed + 1)


def _build(cfg: Config, run_dir: Path, device: torch.device, progress: bool,
           purge_step: int | None = None) -> Trainer:
    """The trainer of a run with everything it is handed: its logger, its method and its task-end hooks."""
    spec = env_spec(cfg.env.domain)
    logger = RunLogger(run_dir, cfg.train.tensorboard, purge_step=purge_step,
                       wandb=wandb_tracker(cfg, run_dir, lambda line: logger.print(line)))
    # Methods may build networks of their own (DRAGO's VAE): seed them like everything else.
    torch.manual_seed(cfg.train.seed)
    method = build_method(cfg, spec, device)
    hooks = []
    if HeldoutRecorder.wanted(cfg):
        hooks.append(HeldoutRecorder(cfg, run_dir, device, logger.print))
    if VisitationRecorder.wanted(cfg):
        hooks.append(VisitationRecorder(cfg, run_dir, logger.print))
    return Trainer(cfg, run_dir, method, spec, logger, device, progress=progress,
                   episode_start=_LazyPreRollout(cfg, run_dir, device) if cfg.transfer.pre_rollout_checkpoint else None,
                   task_end_hooks=hooks,
                   summary_extras=(lambda tasks: {"transfer": transfer_summary(cfg, run_dir, tasks)})
                   if cfg.transfer.checkpoint is not None else None)


class _LazyPreRollout:
    """A transfer's pre-rollout, its learner loaded on the first episode (not by commands that only inspect
    the run); loading moves no random stream, so when it happens changes nothing."""

    def __init__(self, cfg: Config, run_dir: Path, device: torch.device):
        self.cfg, self.run_dir, self.device = cfg, run_dir, device
        self._pre_rollout: PreRollout | None = None

    def __call__(self, env, task_step: int):
        if self._pre_rollout is None:
            self._pre_rollout = PreRollout.from_config(self.cfg, self.run_dir, self.device)
        return self._pre_rollout(env, task_step)


# ---- transfers ---------------------------------------------------------------------------------------
def new_transfer(run_dir: Path, task: str, after: int, out: Path | None = None, force: bool = False,
                 progress: bool = True, **options: Any) -> Trainer:
    """Create the transfer run directory and return its trainer (call ``.run()`` to train).

    ``options`` are :func:`~drago.training.transfer.transfer_config`'s keyword arguments. The directory
    defaults to ``RUN_DIR/transfer/{task}-after{K}``; an existing one is refused unless ``force``.

    Raises:
        RunDirError, ConfigError: one line (unknown task, stage out of range or not finished yet, not a
            run directory, existing transfer directory, bad option).
    """
    cfg, out = plan_transfer(run_dir, task, after, out, **options)
    return new_run(cfg, out, force=force, progress=progress)


def run_transfer(trainer: Trainer) -> dict[str, Any]:
    """Train a transfer run built by :func:`new_transfer` (or resumed) and print its few-shot scores."""
    summary = trainer.run()
    trainer.logger.print(describe(summary))
    trainer.logger.close()
    return summary


def run_paper_cases(run_dir: Path, out: Path | None = None, force: bool = False, progress: bool = True,
                    **options: Any) -> list[dict[str, Any]]:
    """Run the paper's transfer cases of the run's domain one after the other.

    A case whose directory already holds a finished transfer with the same settings is skipped, an
    unfinished one is resumed; ``force`` redoes every case. ``out`` is the folder holding the cases
    (default ``RUN_DIR/transfer``). Every case is checked before the first one starts.

    Returns:
        The summary of each case, in order.
    """
    plans = []
    for task, after, cfg, case_dir in paper_transfer_plan(Path(run_dir), out, **options):
        if case_dir.exists() and any(case_dir.iterdir()) and not force:
            if not is_run_dir(case_dir):
                raise RunDirError(f"{case_dir} is not empty and not a drago run; move it away or pass --force")
            diffs = config_diffs(read_run_config(case_dir), cfg, ignore=())
            if diffs:
                raise RunDirError(f"{case_dir} holds a transfer with other settings ({'; '.join(diffs[:3])}); "
                                  "pass --force to redo it")
        plans.append((task, after, cfg, case_dir))
    summaries = []
    for task, after, cfg, case_dir in plans:
        fresh = force or not is_run_dir(case_dir)
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
