"""What a SLURM job of a study runs on its node: ``python -m drago ARGS`` for each of its members, stopped and
requeued near the time limit (:class:`StudyJob`, pickled by submitit)."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from drago.study.local import PARENT_ENV
from drago.study.plan import DONE, RESUME, START, directory_state, format_duration
from drago.study.slurm.options import DEFAULT_TIME_MIN
from drago.training.rundir import CHECKPOINT_FOLDER, SUMMARY_FILE

__all__ = ["Member", "StudyJob", "gpu_for"]

REPORT_LABEL = "report"
STOP_CHILD_S = 20.0  # how long a stopped drago may take to exit before it is killed


@dataclass
class Member:
    """One drago job inside a SLURM job (several when runs share a GPU)."""

    label: str
    kind: str  # run, transfer or report
    directory: str
    start_argv: list[str]
    log: str
    threads: int

    def argv_now(self) -> list[str] | None:
        """The drago arguments for the directory as it is now; None when its work is finished."""
        if self.kind == REPORT_LABEL:
            return list(self.start_argv)
        state = directory_state(Path(self.directory))
        return {START: list(self.start_argv), RESUME: ["resume", self.directory, "--no-progress"], DONE: None}[state]


def gpu_for(index: int, gpus: int, jobs_per_gpu: int, visible: str | None) -> str | None:
    """The CUDA device (as CUDA_VISIBLE_DEVICES) of the ``index``-th run of a job: its own GPU, or every
    ``jobs_per_gpu`` runs one; None without GPUs."""
    if not gpus:
        return None
    devices = [d for d in (visible or "").split(",") if d.strip()] or [str(i) for i in range(gpus)]
    return devices[(index // max(1, jobs_per_gpu)) % len(devices)]


def _ignore_requeue_signal() -> None:  # in the child before exec: the USR2 is for the job's wrapper, not drago
    signal.signal(signal.SIGUSR2, signal.SIG_IGN)


def _progress_mark(directory: str) -> tuple[float, ...]:
    """When the directory's checkpoints and summary last changed (a new one means the run got further)."""
    folder = Path(directory)
    paths = [folder / SUMMARY_FILE, *sorted((folder / CHECKPOINT_FOLDER).glob("*.pt"))]
    marks = []
    for path in paths:
        with contextlib.suppress(OSError):
            marks.append(path.stat().st_mtime)
    return tuple(marks)


def _reap(child: subprocess.Popen, timeout: float) -> bool:
    """Wait up to ``timeout`` seconds for ``child`` to exit, reaping it with os.waitpid; True once it has."""
    deadline = time.monotonic() + max(0.0, timeout)
    while child.returncode is None:
        try:
            pid, status = os.waitpid(child.pid, os.WNOHANG)
        except ChildProcessError:  # reaped already
            return True
        if pid:
            child.returncode = os.waitstatus_to_exitcode(status)
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


class StudyJob:
    """The function a SLURM job of the study runs (submitit pickles it; :mod:`submitit` calls it on the node).

    It starts ``python -m drago ARGS`` for each member, ``ARGS`` from the member's directory as it is now, with
    the output appended to the member's log, and fails if any of them fails. Near the time limit SLURM sends
    USR2 and submitit calls :meth:`checkpoint`: drago is stopped and the job requeued, to resume.
    """

    def __init__(self, members: Sequence[Member], gpus: int = 0, jobs_per_gpu: int = 1,
                 time_limit_s: float = DEFAULT_TIME_MIN * 60):
        self.members = list(members)
        self.gpus = gpus
        self.jobs_per_gpu = jobs_per_gpu
        self.time_limit_s = time_limit_s
        self._children: dict[str, subprocess.Popen] = {}
        self._started = 0.0
        self._marks: dict[str, tuple[float, ...]] = {}

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.update(_children={}, _started=0.0, _marks={})
        return state

    def _note(self, member: Member, text: str) -> None:
        with contextlib.suppress(OSError), open(member.log, "a") as log:
            log.write(text if text.endswith("\n") else text + "\n")

    def _launch(self, index: int, member: Member, argv: list[str]) -> subprocess.Popen:
        Path(member.log).parent.mkdir(parents=True, exist_ok=True)
        env = {k: v for k, v in os.environ.items() if k != PARENT_ENV}
        env["PYTHONUNBUFFERED"] = "1"
        if member.threads > 0:
            env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(member.threads)
        device = gpu_for(index, self.gpus, self.jobs_per_gpu, os.environ.get("CUDA_VISIBLE_DEVICES"))
        if device is not None:
            env["CUDA_VISIBLE_DEVICES"] = device
        job_id = os.environ.get("SLURM_JOB_ID", "?")
        restarts = os.environ.get("SLURM_RESTART_COUNT")
        where = f"SLURM job {job_id} on {socket.gethostname()}" + (f", restart {restarts}" if restarts else "")
        with open(member.log, "a") as log:
            log.write(f"\n==== {datetime.now().strftime('%Y-%m-%d %H:%M:%S')} drago {' '.join(argv)}  ({where}"
                      + (f", CUDA_VISIBLE_DEVICES={device}" if device is not None else "") + ")\n")
            log.flush()
            return subprocess.Popen([sys.executable, "-m", "drago", *argv], stdin=subprocess.DEVNULL, stdout=log,
                                    stderr=subprocess.STDOUT, env=env, preexec_fn=_ignore_requeue_signal)

    def __call__(self) -> dict[str, int]:
        self._started = time.time()
        self._marks = {m.label: _progress_mark(m.directory) for m in self.members}
        self._children = {}
        for index, member in enumerate(self.members):
            argv = member.argv_now()
            if argv is None:
                self._note(member, f"==== {datetime.now().strftime('%Y-%m-%d %H:%M:%S')} {member.directory} is "
                                   "complete: nothing to do")
                continue
            self._children[member.label] = self._launch(index, member, argv)
        # Polled rather than waited for: submitit runs checkpoint() in this thread's USR2 handler, and a
        # Popen.wait() interrupted by it would hold the lock every other wait() on that child needs.
        while any(child.poll() is None for child in self._children.values()):
            time.sleep(0.5)
        codes = {label: child.returncode for label, child in self._children.items()}
        failed = [(label, code) for label, code in codes.items() if code != 0]
        if failed:
            logs = {m.label: m.log for m in self.members}
            raise RuntimeError("; ".join(f"{label}: drago exited with {code} (log {logs[label]})"
                                         for label, code in failed))
        return codes

    def _stop_children(self) -> None:
        """SIGTERM to every child (drago stops as on Ctrl-C), SIGKILL to those still there after STOP_CHILD_S.

        Runs inside a signal handler: children are reaped with os.waitpid, never with Popen's own waits, whose
        lock the interrupted code may hold.
        """
        for child in self._children.values():
            if child.returncode is None:
                with contextlib.suppress(OSError):
                    child.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_CHILD_S
        for child in self._children.values():
            if not _reap(child, deadline - time.monotonic()):
                with contextlib.suppress(OSError):
                    child.kill()
                _reap(child, 10.0)

    def checkpoint(self, *args: Any, **kwargs: Any) -> Any:
        """submitit's hook on USR2 (time limit near, or preemption): stop drago, then requeue this job.

        Returns what submitit requeues (this job again: each member continues with ``drago resume``), or None,
        so that the job ends, when it ran for most of its time limit without writing a single checkpoint: its
        time limit is too short for the run's checkpoint period, and requeueing it would never get further.
        """
        from submitit.helpers import DelayedSubmission

        elapsed = time.time() - self._started if self._started else 0.0
        self._stop_children()
        progressed = any(_progress_mark(m.directory) != self._marks.get(m.label) for m in self.members)
        stamp = datetime.now().strftime("%Y-%m-%d %H:%M:%S")
        job_id = os.environ.get("SLURM_JOB_ID", "?")
        if not progressed and elapsed >= 0.5 * self.time_limit_s:
            for member in self.members:
                self._note(member, f"==== {stamp} SLURM job {job_id} stopped near its time limit after "
                                   f"{format_duration(elapsed)} without a new checkpoint: not requeued (it would "
                                   "never get further). Raise --time or lower train.checkpoint_freq; the study "
                                   "command continues it.")
            return None
        for member in self.members:
            self._note(member, f"==== {stamp} SLURM job {job_id} stopped (time limit near, or preempted) after "
                               f"{format_duration(elapsed)}: requeued, it continues from the last checkpoint")
        return DelayedSubmission(self)
