"""The local backend of ``drago study``: the plan's jobs as child processes on this machine.

Jobs run as child processes, ``jobs`` at a time, each new run with ``train.threads`` = cores // jobs;
each child's output goes to ``OUT/logs/``. A child dies with the study (Linux), so a restarted study
never races an orphan for a run directory, and a lock file keeps two studies out of one folder.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from drago.study.plan import (DONE, Job, StudyError, StudyPlan, format_duration, job_outcome, record_verdict,
                              summary_line)
from drago.study.report import write_report

__all__ = ["StudyResult", "become_child", "run_study", "study_lock"]

LOCK_FILE = ".study.lock"
PARENT_ENV = "DRAGO_STUDY_PARENT"


@dataclass
class StudyResult:
    """What a study invocation did."""

    plan: StudyPlan
    finished: list[Job]
    failed: list[Job]
    blocked: list[Job]
    report: list[Path]
    report_error: str | None = None

    @property
    def ok(self) -> bool:
        return not self.failed and not self.blocked and self.report_error is None

    def summary_line(self) -> str:
        failures = [(job, f"exit {job.returncode}, log {job.log}") for job in self.failed]
        return summary_line(self.plan, self.finished, failures, self.blocked, self.report_error)


def _waits_for(job: Job) -> list[Job]:
    return [*([job.source] if job.source is not None else []), *job.needs]


class _Done:
    """A job run in this process: finished when launched."""

    def __init__(self, returncode: int):
        self.returncode = returncode

    def poll(self) -> int:
        return self.returncode


def _header(job: Job) -> str:
    return f"\n==== {datetime.now().strftime('%Y-%m-%d %H:%M:%S')} drago {' '.join(job.argv)}\n"


def _launch_process(job: Job) -> subprocess.Popen:
    job.log.parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, PARENT_ENV: str(os.getpid()), "PYTHONUNBUFFERED": "1"}
    if job.threads > 0:
        env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(job.threads)
    with job.log.open("a") as log:
        log.write(_header(job))
        log.flush()
        return subprocess.Popen([sys.executable, "-m", "drago", *job.argv], stdin=subprocess.DEVNULL,
                                stdout=log, stderr=subprocess.STDOUT, env=env)


def _launch_in_process(job: Job, command: Callable[[list[str]], int]) -> _Done:
    job.log.parent.mkdir(parents=True, exist_ok=True)
    with job.log.open("a") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        log.write(_header(job))
        try:
            code = command(job.argv)
        except Exception:  # a crash of the run, as a child process would exit with it
            traceback.print_exc(file=log)
            code = 1
    if code == 130:  # the command line turned Ctrl-C into exit code 130
        raise KeyboardInterrupt
    return _Done(code)


@contextlib.contextmanager
def study_lock(out: Path):
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK_FILE
    with path.open("w") as handle:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            yield
            return
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise StudyError(f"another `drago study` is working in {out} (it holds {path}); "
                             "wait for it to finish or stop it first") from None
        handle.write(f"{os.getpid()}\n")
        handle.flush()
        yield


def _stop(running: dict[Job, Any]) -> None:
    """Interrupt the children and wait for them, killing those that linger.

    SIGTERM rather than SIGINT: children inherit an ignored SIGINT from a study started in the background,
    and ``drago`` handles SIGTERM as it does Ctrl-C.
    """
    for handle in running.values():
        if isinstance(handle, subprocess.Popen) and handle.poll() is None:
            handle.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + 15
    for handle in running.values():
        if isinstance(handle, subprocess.Popen):
            try:
                handle.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                handle.kill()
                handle.wait()


def run_study(plan: StudyPlan, echo: Callable[[str], None] = print,
              in_process: Callable[[list[str]], int] | None = None, poll_seconds: float = 0.2) -> StudyResult:
    """Run every unfinished job of ``plan``, then write the report.

    Jobs run ``plan.jobs`` at a time as child processes (``python -m drago ARGS``, which is ``drago ARGS``
    dying with this process), their output appended to ``job.log``. Runs start before transfers
    (with records, a unit's transfers and record before new runs); a transfer starts once its run has
    finished; if the run fails, its transfers are not started.
    ``in_process``, the command line's ``main``, runs the jobs one after the other in this process
    instead (for tests: a patched function is seen by the runs).

    Raises:
        StudyError: Another study holds the folder's lock.
        KeyboardInterrupt: After the running children were interrupted and have exited.
    """
    launch: Callable[[Job], Any] = (_launch_process if in_process is None
                                    else lambda job: _launch_in_process(job, in_process))
    todo = [job for job in [*plan.ordered, *plan.record_jobs] if job.state != DONE]
    total, count = len(todo), 0
    finished: list[Job] = []
    running: dict[Job, Any] = {}

    def line(job: Job, text: str) -> None:
        nonlocal count
        count += 1
        echo(f"[{count}/{total}] {text}")

    with study_lock(plan.out):
        try:
            while todo or running:
                for job in [j for j in todo if any(n.status in ("failed", "blocked") for n in _waits_for(j))]:
                    todo.remove(job)
                    job.status = "blocked"
                    why = "its run" if job.kind == "transfer" else "a job of its unit"
                    line(job, f"not started: {job.label} ({why} failed)")
                # Without records, runs before transfers: a run is the longest job and unlocks four, so
                # starting runs first keeps the cores busy to the end instead of leaving one last run alone.
                # With records, finishing units comes first (record, then transfers): a study stopped at any
                # time keeps every unit it could finish.
                order = ("record", "transfer", "run") if plan.records is not None else ("run", "transfer")
                ready = sorted((j for j in todo if all(n.status == "done" for n in _waits_for(j))),
                               key=lambda j: order.index(j.kind))
                while ready and len(running) < plan.jobs:
                    job = ready.pop(0)
                    todo.remove(job)
                    job.status, job.seconds = "running", time.monotonic()
                    running[job] = launch(job)
                ended = [(job, handle.poll()) for job, handle in running.items()]
                ended = [(job, code) for job, code in ended if code is not None]
                if not ended:
                    if not running and todo:  # cannot happen: every transfer waits on a run of the plan
                        raise RuntimeError(f"study jobs wait on nothing: {', '.join(j.label for j in todo)}")
                    time.sleep(poll_seconds)
                    continue
                for job, code in ended:
                    del running[job]
                    job.returncode, job.seconds = code, time.monotonic() - job.seconds
                    mismatch = record_verdict(job.record, job.protocol) if code == 0 and job.kind == "record" else None
                    if mismatch:  # the next study would run the unit again: say so now, not then
                        code = job.returncode = 1
                        with job.log.open("a") as log:
                            log.write(f"drago study: the record does not have the study's protocol: {mismatch}\n")
                    if code == 0:
                        job.status = "done"
                        finished.append(job)
                        outcome = job_outcome(job)
                        line(job, f"done    {job.label} in {format_duration(job.seconds)}"
                             + (f": {outcome}" if outcome else ""))
                    else:
                        job.status = "failed"
                        line(job, f"FAILED  {job.label} (exit {code}); log: {job.log}")
        except KeyboardInterrupt:
            _stop(running)
            raise
        report, error = write_report(plan, echo)
    failed = [j for j in plan.ordered if j.status == "failed"]
    blocked = [j for j in plan.ordered if j.status == "blocked"]
    return StudyResult(plan, finished, failed, blocked, report, error)


# ---------------------------------------------------------------------------------------------------
# a study's child process
# ---------------------------------------------------------------------------------------------------
def _die_with_parent() -> None:
    """Ask Linux to SIGKILL this process when its parent (the study) dies; elsewhere do nothing."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def become_child() -> bool:
    """Make this process a study job that does not outlive its study; False if the study is already gone.

    ``python -m drago`` calls it when it was started by a study (the study sets the variable it reads).
    """
    _die_with_parent()
    parent = os.environ.get(PARENT_ENV)
    return not (parent and os.getppid() != int(parent))  # the study died before the line above took effect
