"""Weights & Biases tracking of a run (``train.wandb``; docs: Command line and configs, Experiment tracking).

wandb is imported only by a run that logs to it. It receives the scalars TensorBoard receives, with the same
tags and the same step (:func:`drago.training.logger.scalars`), so W&B's step axis is TensorBoard's global
env step, and the run's whole config.

A resumed drago run continues the same W&B run, whose id ``RUN_DIR/wandb.json`` keeps. W&B holds one row per
step and accepts only steps after the last one it holds (docs.wandb.ai, "Resume a run"). The resumed process
replays the steps between its checkpoint and the point where the killed one stopped; drago does not send
the ones W&B already holds, so W&B keeps the values the killed process logged there (the same values on the
same CPU: runs are reproducible). W&B's rewind (``resume_from``), which would replace them, is a preview
of its cloud service that offline runs cannot use.
"""

from __future__ import annotations

import importlib.util
import json
import os
import secrets
import string
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from drago.config import Config, ConfigError
from drago.training.rundir import read_wandb_run, write_wandb_run

INSTALL_HINT = "pip install 'drago[wandb]'"


class TrackingError(ConfigError):
    """Weights & Biases cannot be used as configured; the message is one line."""


def check_tracking(cfg: Config) -> None:
    """Refuse a run that should log to W&B when wandb is not installed (before the run touches its directory).

    Raises:
        TrackingError: one line naming the extra to install.
    """
    if cfg.train.wandb != "off" and importlib.util.find_spec("wandb") is None:
        raise TrackingError(f"train.wandb={cfg.train.wandb} needs Weights & Biases, which is not installed: "
                            f"{INSTALL_HINT}")


def default_run_name(cfg: Config) -> str:
    """``PRESET/METHOD/seedS``, and ``.../transfer/TASK-afterK`` for a transfer run."""
    name = f"{cfg.preset}/{cfg.method.name}/seed{cfg.train.seed}"
    if cfg.transfer.checkpoint is not None:
        name += f"/transfer/{cfg.transfer.case or cfg.env.tasks[0]}-after{cfg.transfer.after}"
    return name


def wandb_tracker(cfg: Config, run_dir: Path, say: Callable[[str], None]) -> WandbTracker | None:
    """The run's W&B sink, or None when ``train.wandb`` is off (then nothing imports wandb)."""
    if cfg.train.wandb == "off":
        return None
    check_tracking(cfg)
    return WandbTracker(cfg, run_dir, say)


class WandbTracker:
    """A drago run's W&B run, started at the first logged row, so that a resumed run with nothing left to do
    opens none. ``say`` prints a line to the run's console."""

    def __init__(self, cfg: Config, run_dir: Path, say: Callable[[str], None]):
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self._say = say
        self._run: Any = None
        self._first_step = 0  # the steps below this one are in W&B already (see the module docstring)

    def log(self, values: dict[str, float | int], step: int) -> None:
        if self._run is None:
            self._start()
        if step >= self._first_step:
            self._run.log(values, step=step)

    def close(self) -> None:
        if self._run is None:
            return
        run, self._run = self._run, None
        # Called from `finally` blocks too (drago.api.train): a run ended by an exception is marked failed.
        run.finish(exit_code=1 if sys.exc_info()[0] is not None else 0)

    def _start(self) -> None:
        try:
            import wandb
        except ImportError as err:
            raise TrackingError(f"train.wandb={self.cfg.train.wandb} needs Weights & Biases, which cannot be "
                                f"imported ({err}): {INSTALL_HINT}") from None
        train = self.cfg.train
        known = read_wandb_run(self.run_dir) or {}
        run_id = known.get("id") or _new_run_id()
        entity = train.wandb_entity or known.get("entity") or None
        if not known:
            # On disk before the W&B run exists: a process killed at any moment after this is continued under it.
            write_wandb_run(self.run_dir, {"id": run_id, "project": train.wandb_project, "entity": entity})
        try:
            run = wandb.init(
                project=train.wandb_project, entity=entity, id=run_id, resume="allow", mode=train.wandb,
                name=train.wandb_name or default_run_name(self.cfg), group=train.wandb_group,
                tags=list(train.wandb_tags) or None,
                job_type="transfer" if self.cfg.transfer.checkpoint is not None else "train",
                config=self.cfg.to_dict(),
                # W&B's files stay with the run unless WANDB_DIR says otherwise (read here: W&B reads the
                # environment once per process).
                dir=os.environ.get("WANDB_DIR") or str(self.run_dir),
                # Never hand back or finish a W&B run the caller has open (drago.train from a notebook).
                reinit="create_new")
        except Exception as err:  # noqa: BLE001 - W&B raises more than wandb.errors.Error (its service's errors)
            first_line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise TrackingError(f"Weights & Biases could not start run {run_id}: {first_line} (or log offline: "
                                "train.wandb=offline, then `wandb sync`)") from None
        if run.entity and run.entity != entity:
            # W&B chose the default entity: keep it, so a resume goes to the same place after that default changes.
            write_wandb_run(self.run_dir, {"id": run_id, "project": run.project, "entity": run.entity})
        self._run = run
        self._first_step = run.step
        if run.offline:
            last = self._last_offline_step(Path(run.dir).parent)
            if last is not None:
                self._first_step = max(self._first_step, last + 1)
        if self._first_step > 0:
            self._say(f"W&B: continuing run {run_id}, which holds the steps up to {self._first_step - 1}; "
                      "those are not sent again")

    def _last_offline_step(self, segment: Path) -> int | None:
        """The last step that the earlier offline processes of this W&B run wrote to their transaction logs
        (``offline-run-*-ID/run-ID.wandb`` next to ``segment``, this process's folder): W&B itself starts a
        resumed offline run at step 0. A log cut short by a kill holds what was written before it."""
        earlier = sorted((d for d in segment.parent.glob(f"offline-run-*-{self._run.id}") if d != segment),
                         reverse=True)
        for folder in earlier:  # newest first: each holds only steps after those of the ones before it
            for log in sorted(folder.glob("run-*.wandb")):
                try:
                    step = last_logged_step(log)
                except TrackingError as err:
                    self._say(f"W&B: {err}; this process logs every step after its checkpoint, and "
                              "`wandb sync` may meet some steps twice")
                    return None
                if step is not None:
                    return step
        return None


def last_logged_step(log: Path) -> int | None:
    """The last step in a W&B transaction log (``run-ID.wandb``), None when it holds none, read with W&B's own
    reader (``wandb leet inspect --summary --json``, shipped with wandb 0.31).

    Raises:
        TrackingError: the reader is missing or fails.
    """
    try:
        done = subprocess.run([sys.executable, "-m", "wandb", "leet", "inspect", "--summary", "--json", str(log)],
                              capture_output=True, text=True, timeout=600,
                              env={**os.environ, "WANDB_MODE": "offline", "WANDB_ERROR_REPORTING": "false",
                                   "WANDB_DIR": str(Path(log).parent.parent)})  # its own log goes there too
    except (OSError, subprocess.TimeoutExpired) as err:
        raise TrackingError(f"could not read {log} ({err})") from None
    try:
        summary = json.loads(done.stdout) if done.returncode == 0 else None
    except json.JSONDecodeError:
        summary = None
    if not isinstance(summary, dict):
        why = (done.stderr.strip().splitlines() or ["no summary"])[-1]
        raise TrackingError(f"could not read {log} with `wandb leet inspect` ({why})")
    step = summary.get("step")
    return step if isinstance(step, int) else None


def _new_run_id() -> str:
    """Eight lowercase letters and digits, the form of W&B's own run ids."""
    return "".join(secrets.choice(string.ascii_lowercase + string.digits) for _ in range(8))
