"""The run directory: the one owner of its file names, its readers and writers, and its atomic writes.

A run directory holds (see the docs page "Getting started", section "What a run directory holds")::

    config.yaml            the resolved config the run was started with
    summary.json           per-task results, rewritten at the end of every task
    train.csv eval.csv timing.csv   the logs (drago.training.logger)
    checkpoints/task<k>_<name>.pt   the state after task k (1-based stage k)
    checkpoints/resume.pt           the latest snapshot of the task in progress
    heldout/task<k>_<name>.npz      DeepMind Control: task k's held-out transitions
    transfer/<task>-after<K>/       transfer runs learned from this run's stage K
    wandb.json             train.wandb: the Weights & Biases run this run logs to (its id), so a
                           resumed run continues it
    wandb/                 train.wandb: W&B's own files (unless WANDB_DIR says elsewhere)

Everything that reads or writes one of these names goes through this module, so the format has one
definition and every write is atomic: a crash at any moment leaves either the old file or the new one.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import signal
import tempfile
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import yaml

from drago.config import Config, migrate_saved, setting_fields

CONFIG_FILE = "config.yaml"
SUMMARY_FILE = "summary.json"
CHECKPOINT_FOLDER = "checkpoints"
RESUME_FILE = "resume.pt"
HELDOUT_FOLDER = "heldout"
TRANSFER_FOLDER = "transfer"
WANDB_RUN_FILE = "wandb.json"
VISITATION_FILE = "visitation.csv"  # grid runs: where each agent went (training/visitation.py)
#: Agent settings whose default changed after runs were written without them: the value such a run used.
LEGACY_TDMPC_DEFAULTS = {"precision": "float32", "compile": "false", "fast_tanh": False}

#: Settings that never make two runs "different runs": the thread count follows the machine (a study's
#: --jobs), and where a run's results are also sent (Weights & Biases) changes none of them; a resumed run
#: keeps the values it was started with.
SETTINGS_THAT_MAY_DIFFER: tuple[str, ...] = ("train.threads", "train.wandb", "train.wandb_project",
                                             "train.wandb_entity", "train.wandb_group", "train.wandb_tags",
                                             "train.wandb_name")

#: Settings a run resolves for its machine when it starts (drago.agent.speed): ``auto`` wanted agrees with
#: whatever the run chose.
RESOLVED_AT_START: tuple[str, ...] = ("agent.tdmpc.precision", "agent.tdmpc.compile")


class RunDirError(ValueError):
    """A run directory that cannot be used as asked; the message is one line."""


# ---- atomic writes ---------------------------------------------------------------------------------
def atomic_write(path: str | Path, write: Callable[[IO[bytes]], None], durable: bool = True) -> Path:
    """Write a file through ``write(handle)`` so that a crash leaves either the old file or the new one.

    The bytes go to a temporary file in the same folder, which then replaces ``path`` by an atomic
    rename. ``durable`` also flushes the file and its folder to disk before returning, so the new file
    survives a power loss (checkpoints); logs and tables that are cheap to rewrite skip it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A process killed mid-write leaves its temporary file behind; the next write of the same file clears it.
    for stale in path.parent.glob(f".{path.name}.*.tmp"):
        stale.unlink(missing_ok=True)
    with _interrupts_held():
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as handle:
                write(handle)
                if durable:
                    handle.flush()
                    os.fsync(handle.fileno())
            os.chmod(tmp, 0o644)  # mkstemp creates owner-only files; run directories are meant to be shared
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        if durable:
            dir_fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
    return path


@contextlib.contextmanager
def _interrupts_held():
    """Hold Ctrl-C and SIGTERM until the block is done, then raise them as their handlers would have.

    A writer interrupted halfway can fail in its own clean-up (``torch.save``'s zip writer raises a
    ``RuntimeError`` about the stream's position), which would replace the interrupt with a crash; held, the
    write completes, and the command stops right after it the way it would have anyway.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    handlers = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(signum)
        if callable(handler):  # an ignored or default signal keeps its behaviour: nothing to raise later
            handlers[signum] = handler
            signal.signal(signum, lambda received, frame: held.append(received))
    try:
        yield
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
    if held:
        handlers[held[0]](held[0], None)


def atomic_write_text(path: str | Path, text: str, durable: bool = False) -> Path:
    """:func:`atomic_write` of UTF-8 text."""
    return atomic_write(path, lambda handle: handle.write(text.encode("utf-8")), durable=durable)


# ---- config and summary ----------------------------------------------------------------------------
def write_rows_csv(rows: list[dict[str, Any]], columns: tuple[str, ...], path: str | Path) -> Path:
    """Write measurement rows to ``path`` atomically; floats as ``repr`` so the file reads back bit-exactly."""
    handle = io.StringIO(newline="")
    writer = csv.DictWriter(handle, fieldnames=list(columns), extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: repr(v) if isinstance(v, float) and math.isfinite(v) else v for k, v in row.items()})
    return atomic_write_text(path, handle.getvalue())


def is_run_dir(path: str | Path) -> bool:
    return (Path(path) / CONFIG_FILE).is_file()


def write_run_config(run_dir: str | Path, cfg: Config) -> Path:
    return atomic_write_text(Path(run_dir) / CONFIG_FILE, yaml.safe_dump(cfg.to_dict(), sort_keys=False))


def read_run_config(run_dir: str | Path) -> Config:
    """The resolved config a run directory was started with.

    Raises:
        RunDirError: no such directory, no ``config.yaml``, or one that is not a drago config.
        drago.config.ConfigError: a config whose values are invalid.
    """
    run_dir = Path(run_dir)
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
    data = migrate_saved(data)
    tdmpc = data.get("agent", {}).get("tdmpc") if isinstance(data.get("agent"), dict) else None
    if isinstance(tdmpc, dict):
        # Runs written before these settings existed computed with their values of then, not today's defaults.
        for key, then in LEGACY_TDMPC_DEFAULTS.items():
            tdmpc.setdefault(key, then)
    return Config.from_dict(data)


def write_summary(run_dir: str | Path, summary: dict[str, Any]) -> Path:
    return atomic_write_text(Path(run_dir) / SUMMARY_FILE, json.dumps(summary, indent=2) + "\n")


def read_summary(run_dir: str | Path, error: type[RunDirError] = RunDirError) -> dict[str, Any] | None:
    """``summary.json``, or None before the run's first task finished.

    Raises:
        error: the file is unreadable or not a drago run summary.
    """
    file = Path(run_dir) / SUMMARY_FILE
    if not file.exists():
        return None
    try:
        data = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise error(f"{file} is not readable JSON ({err})") from None
    if not isinstance(data, dict) or not isinstance(data.get("tasks"), list) or not all(
            isinstance(t, dict) and "name" in t for t in data["tasks"]):
        raise error(f"{file} is not a drago run summary (no list of tasks with names)")
    return data


def is_complete(run_dir: str | Path) -> bool:
    """True when the run's summary says every planned task has finished (False for anything unreadable)."""
    try:
        summary = read_summary(run_dir)
    except RunDirError:
        return False
    return summary is not None and summary.get("complete") is True


# ---- Weights & Biases ------------------------------------------------------------------------------
def read_wandb_run(run_dir: str | Path) -> dict[str, Any] | None:
    """``wandb.json``: the W&B run (``id``, ``project``, ``entity``) a run logs to, or None before its first
    W&B run started (or when the file is unreadable: the run then starts a new W&B run)."""
    file = Path(run_dir) / WANDB_RUN_FILE
    try:
        data = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("id"), str) and data["id"] else None


def write_wandb_run(run_dir: str | Path, run: dict[str, Any]) -> Path:
    return atomic_write_text(Path(run_dir) / WANDB_RUN_FILE, json.dumps(run, indent=2) + "\n", durable=True)


# ---- checkpoints -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class RunCheckpoint:
    """One task checkpoint of a run: stage = task index + 1."""

    stage: int
    task: str
    path: Path


def task_checkpoint_path(run_dir: str | Path, tasks: Sequence[str], stage: int) -> Path:
    """Where a run saves its state after its ``stage``-th task (1-based): ``checkpoints/task<k>_<name>.pt``."""
    return Path(run_dir) / CHECKPOINT_FOLDER / f"task{stage}_{tasks[stage - 1]}.pt"


def resume_checkpoint_path(run_dir: str | Path) -> Path:
    return Path(run_dir) / CHECKPOINT_FOLDER / RESUME_FILE


def heldout_path(run_dir: str | Path, stage: int, task: str) -> Path:
    """``RUN_DIR/heldout/task<stage>_<task>.npz``; stage = task index + 1."""
    return Path(run_dir) / HELDOUT_FOLDER / f"task{stage}_{task}.npz"


def finished_task_checkpoints(run_dir: str | Path, cfg: Config) -> list[RunCheckpoint]:
    """The task checkpoints a run has written so far, in stage order."""
    found = [RunCheckpoint(stage=k, task=name, path=task_checkpoint_path(run_dir, cfg.env.tasks, k))
             for k, name in enumerate(cfg.env.tasks, start=1)]
    return [c for c in found if c.path.is_file()]


def run_checkpoints(run_dir: str | Path, error: type[RunDirError] = RunDirError,
                    domain_check: Callable[[Config], str | None] | None = None) -> tuple[Config, list[RunCheckpoint]]:
    """The run's config and its finished tasks' checkpoints, in task order (files only: cheap, so a command
    given several runs can refuse a bad one before evaluating any).

    Args:
        error: the error type to raise (an evaluation's own subclass of :class:`RunDirError`).
        domain_check: returns why the run's domain does not suit the caller, or None when it does.

    Raises:
        error: not a run directory, a domain the caller refuses, or no task finished yet.
        drago.config.ConfigError: the run's ``config.yaml`` is invalid.
    """
    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir)
    refusal = domain_check(cfg) if domain_check is not None else None
    if refusal is not None:
        raise error(f"{run_dir} is a '{cfg.env.domain}' run; {refusal}")
    found = finished_task_checkpoints(run_dir, cfg)
    if not found:
        raise error(f"{run_dir} has no task checkpoint yet (the first task has not finished)")
    return cfg, found


# ---- comparing runs --------------------------------------------------------------------------------
def config_diffs(existing: Config, wanted: Config, ignore: Sequence[str] = SETTINGS_THAT_MAY_DIFFER) -> list[str]:
    """``key: value there, value here`` for every setting in which two configs differ (values compared
    after a round trip through a run's ``config.yaml``, so a tuple and the list it is saved as agree; an
    ``auto`` here agrees with the value a run resolved it to, see :data:`RESOLVED_AT_START`)."""
    there, here = flat_settings(existing), flat_settings(wanted)
    return [f"{key}: {there.get(key)!r} there, {here.get(key)!r} here" for key in dict.fromkeys([*here, *there])
            if key not in ignore and there.get(key) != here.get(key)
            and not (key in RESOLVED_AT_START and here.get(key) == "auto")]


def flat_settings(cfg: Config) -> dict[str, Any]:
    """``{"section.key": value}`` of every setting (``agent.tdmpc.horizon``; a plug-in method's own settings as
    one ``method.options`` mapping), as a run's ``config.yaml`` stores it (tuples as lists)."""
    data = Config.from_dict(cfg.to_dict()).to_dict()
    out: dict[str, Any] = {"preset": data["preset"]}
    for key, _, _ in setting_fields():
        value = data
        for part in key.split("."):
            value = value[part]
        out[key] = value
    return out
