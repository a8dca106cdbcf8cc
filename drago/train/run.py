"""Build a trainer from a config (new run) or from a run directory (resume): the composition root."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import torch
import yaml

from drago.config import Config, ConfigError
from drago.continual import build_method
from drago.envs import env_spec
from drago.train.checkpoint import load_checkpoint
from drago.train.logger import RunLogger
from drago.train.resources import keep_freed_memory
from drago.train.trainer import Trainer

CONFIG_FILE = "config.yaml"


class RunDirError(ValueError):
    """A run directory that cannot be used as asked; the message is one line."""


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
    set_threads(cfg.train.threads)
    keep_freed_memory()


def new_run(cfg: Config, run_dir: Path, force: bool = False, progress: bool = True) -> Trainer:
    """Create ``run_dir`` for ``cfg`` (refusing to overwrite a run unless ``force``) and build its trainer."""
    device = resolve_device(cfg.train.device)
    _prepare_process(cfg)
    if run_dir.exists() and any(run_dir.iterdir()):
        if not force:
            raise RunDirError(f"run directory {run_dir} already exists; pass --force to overwrite it "
                              f"or `drago resume {run_dir}` to continue it")
        if not (run_dir / CONFIG_FILE).exists():
            raise RunDirError(f"{run_dir} is not empty and not a drago run; refusing to delete it, choose another --out")
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / CONFIG_FILE).write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    trainer = _build(cfg, run_dir, device, progress)
    trainer.logger = RunLogger(run_dir, cfg.train.tensorboard)
    return trainer


def read_run_config(run_dir: Path) -> Config:
    """The resolved config a run directory was started with."""
    config_path = run_dir / CONFIG_FILE
    if not run_dir.exists():
        raise RunDirError(f"run directory {run_dir} does not exist")
    if not config_path.is_file():
        raise RunDirError(f"{run_dir} is not a drago run directory (no {CONFIG_FILE})")
    try:
        data = yaml.safe_load(config_path.read_text())
    except yaml.YAMLError as err:
        raise RunDirError(f"{config_path} is not valid YAML ({str(err).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise RunDirError(f"{config_path} does not hold a drago config")
    return Config.from_dict(data)


def resume(run_dir: Path, progress: bool = True) -> Trainer:
    """Rebuild the trainer of an existing run; it continues where the last checkpoint left off."""
    cfg = read_run_config(run_dir)
    device = resolve_device(cfg.train.device)
    _prepare_process(cfg)
    trainer = _build(cfg, run_dir, device, progress)
    # Read every finished task's checkpoint now, so a damaged one fails before any work starts.
    for index in range(trainer.completed_tasks()):
        load_checkpoint(trainer.task_checkpoint(index), kind="task", domain=cfg.env.domain)
    # TensorBoard must forget the events written after the checkpoint the run continues from.
    if trainer.resume_checkpoint.exists():
        state = load_checkpoint(trainer.resume_checkpoint, kind="resume", domain=cfg.env.domain)
        purge = trainer.global_env_step(index=state["task_index"], step=state["step"])
    else:
        purge = trainer.global_env_step(index=trainer.completed_tasks())
    trainer.logger = RunLogger(run_dir, cfg.train.tensorboard, purge_step=purge)
    return trainer


def _build(cfg: Config, run_dir: Path, device: torch.device, progress: bool) -> Trainer:
    spec = env_spec(cfg.env.domain)
    # Methods may build networks of their own (DRAGO's VAE): seed them like everything else.
    torch.manual_seed(cfg.train.seed)
    method = build_method(cfg, spec, device)
    trainer = Trainer(cfg, run_dir, method, spec, None, device, progress=progress)
    return trainer
