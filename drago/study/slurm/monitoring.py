"""What SLURM and the study folder say about a SLURM study's jobs: ``OUT/slurm/jobs.json``, ``squeue``'s states,
why a job failed, following the jobs to their end (``--wait``) and ``drago study --status``."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drago.study.local import LOCK_FILE
from drago.study.plan import (DONE, LOG_FOLDER, RESUME, Job, StudyError, StudyPlan, directory_state, format_duration,
                              job_outcome, job_wall_time, records_status, summary_line)
from drago.study.slurm.node import REPORT_LABEL
from drago.training.rundir import atomic_write_text

if TYPE_CHECKING:
    from drago.study.slurm.submission import Submission

__all__ = ["Record", "SlurmResult", "SlurmState", "active_job_ids", "failure_reason", "query_states", "slurm_dir",
           "status_lines", "wait_study"]

SLURM_FOLDER = "slurm"  # OUT/slurm: jobs.json, shared.json, submitit/ (scripts, pickles, SLURM's own logs)
JOBS_FILE = "jobs.json"
SUBMITIT_FOLDER = "submitit"

# squeue's job states (man squeue, JOB STATE CODES). A job is "active" until it ends; requeued jobs are active.
RUNNING_STATES = frozenset({"RUNNING", "COMPLETING", "CONFIGURING", "SIGNALING", "STAGE_OUT", "RESIZING"})
QUEUED_STATES = frozenset({"PENDING", "REQUEUED", "REQUEUE_FED", "REQUEUE_HOLD", "SPECIAL_EXIT", "SUSPENDED",
                           "STOPPED", "RESV_DEL_HOLD", "POWER_UP_NODE"})
ACTIVE_STATES = RUNNING_STATES | QUEUED_STATES
NEVER_SATISFIED = "DependencyNeverSatisfied"


# ---------------------------------------------------------------------------------------------------
# the study folder's record of its jobs
# ---------------------------------------------------------------------------------------------------
def slurm_dir(out: Path) -> Path:
    return Path(out) / SLURM_FOLDER


@dataclass
class Record:
    """``OUT/slurm/jobs.json``: every job the study submitted, and the latest job of each label."""

    path: Path
    jobs: dict[str, dict[str, Any]] = field(default_factory=dict)  # job id -> labels, kind, after, name, ...
    latest: dict[str, str] = field(default_factory=dict)  # label -> job id (REPORT_LABEL for the report)
    check: str | None = None  # a shared-folder check job not yet seen to finish

    @classmethod
    def load(cls, out: Path) -> Record:
        path = slurm_dir(out) / JOBS_FILE
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            return cls(path)
        except (OSError, ValueError) as err:
            raise StudyError(f"cannot read {path} ({err}); it lists the study's SLURM jobs: repair or delete it "
                             "once none of them is queued or running") from None
        return cls(path, dict(data.get("jobs", {})), dict(data.get("latest", {})), data.get("check"))

    def save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path, json.dumps({"jobs": self.jobs, "latest": self.latest, "check": self.check},
                                                indent=1) + "\n", durable=True)

    def add(self, job_id: str, labels: Sequence[str], kind: str, after: Sequence[str], name: str,
            argv: Sequence[str]) -> None:
        self.jobs[job_id] = {"labels": list(labels), "kind": kind, "after": list(after), "name": name,
                             "submitted": datetime.now().isoformat(timespec="seconds"), "argv": list(argv)}
        for label in labels:
            self.latest[label] = job_id


# ---------------------------------------------------------------------------------------------------
# asking SLURM
# ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SlurmState:
    """One line of ``squeue -t all``."""

    job_id: str
    state: str
    reason: str = ""
    elapsed: str = ""
    node: str = ""

    @property
    def active(self) -> bool:
        return self.state in ACTIVE_STATES

    @property
    def running(self) -> bool:
        return self.state in RUNNING_STATES

    def describe(self) -> str:
        text = f"{self.state}"
        if self.running and self.elapsed:
            text += f" {self.elapsed}" + (f" on {self.node}" if self.node and not self.node.startswith("(") else "")
        elif self.reason and self.reason not in ("None", "(null)"):
            text += f" ({self.reason})"
        return text


def query_states() -> tuple[dict[str, SlurmState] | None, str | None]:
    """Every job of this user that slurmctld knows, finished ones included (for ``MinJobAge``), or (None, why)."""
    cmd = ["squeue", "-h", "-t", "all", "-u", str(os.getuid()), "-o", "%i|%T|%r|%M|%N"]
    try:
        proc = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=60,
                              stdin=subprocess.DEVNULL)
    except (OSError, subprocess.SubprocessError) as err:
        return None, f"squeue: {err}"
    if proc.returncode != 0:
        lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
        return None, lines[-1] if lines else f"squeue exited with {proc.returncode}"
    states = {}
    for line in proc.stdout.splitlines():
        parts = line.strip().split("|")
        if len(parts) >= 2 and parts[0]:
            parts += [""] * (5 - len(parts))
            states[parts[0]] = SlurmState(parts[0], parts[1].strip(), parts[2].strip(), parts[3].strip(),
                                          parts[4].strip())
    return states, None


def _elapsed_s(text: str) -> float | None:
    """squeue's elapsed time (``M:SS``, ``H:MM:SS``, ``D-HH:MM:SS``) in seconds."""
    match = re.fullmatch(r"(?:(\d+)-)?(?:(\d+):)?(\d+):(\d+)", text.strip())
    if not match:
        return None
    days, hours, minutes, seconds = (int(x or 0) for x in match.groups())
    return ((days * 24 + hours) * 60 + minutes) * 60 + seconds


def active_job_ids(out: Path) -> list[str]:
    """Ids of this study's SLURM jobs that are queued or running (none where SLURM cannot be asked)."""
    record = Record.load(Path(out))
    if not record.jobs or shutil.which("squeue") is None:
        return []
    states, _ = query_states()
    return [job_id for job_id in record.jobs if states and job_id in states and states[job_id].active]



# ---------------------------------------------------------------------------------------------------
# following the jobs
# ---------------------------------------------------------------------------------------------------
def last_error(*paths: Path) -> str | None:
    """The last line of a log that reads like an error (else its last line), from the first log that has one."""
    pattern = re.compile(r"error|exception|traceback|interrupted|killed|cancelled|time limit|not requeued|failed",
                         re.IGNORECASE)
    for path in paths:
        try:
            with open(path, "rb") as handle:
                handle.seek(0, os.SEEK_END)
                handle.seek(max(0, handle.tell() - 65536))
                lines = [line.strip() for line in handle.read().decode(errors="replace").splitlines()]
        except OSError:
            continue
        lines = [line for line in lines if line and not line.startswith("====")]
        if not lines:
            continue
        matching = [line for line in lines if pattern.search(line)]
        return (matching or lines)[-1][:300]
    return None


def _slurm_log(out: Path, job_id: str, suffix: str) -> Path:
    return slurm_dir(out) / SUBMITIT_FOLDER / f"{job_id}_0_log.{suffix}"


def failure_reason(plan: StudyPlan, job_id: str, state: SlurmState | None, log: Path) -> str:
    what = f"job {job_id} {state.state}" if state else f"job {job_id}, no longer known to SLURM"
    if state is not None and state.reason == NEVER_SATISFIED:
        return f"job {job_id} never started: a job it waited for failed"
    err_log, out_log = _slurm_log(plan.out, job_id, "err"), _slurm_log(plan.out, job_id, "out")
    if not log.exists() and not err_log.exists() and not out_log.exists():
        if state is None or state.state == "CANCELLED":
            return f"{what} before it started"
        return (f"{what}; it wrote no log: can the nodes write {plan.out}? (the study folder must be on a "
                "filesystem they share)")
    error = last_error(log, err_log)
    return f"{what}; log: {log}" + (f"; last error: {error}" if error else "")


@dataclass
class SlurmResult:
    """What ``wait_study`` saw."""

    plan: StudyPlan
    finished: list[Job]
    failed: list[tuple[Job, str]]
    blocked: list[Job]
    report_error: str | None

    @property
    def ok(self) -> bool:
        return not self.failed and not self.blocked and self.report_error is None

    def summary_line(self) -> str:
        return summary_line(self.plan, self.finished, self.failed, self.blocked, self.report_error,
                            ran="run through SLURM")


def wait_study(submission: Submission, echo: Callable[[str], None] = print, poll_seconds: float = 2.0,
               max_poll_seconds: float = 10.0, timeout: float | None = None) -> SlurmResult:
    """Follow the submitted jobs until SLURM is done with them; one line per finished job, as the local backend.

    A job's end is read from ``squeue -t all`` and its directory: done when its summary says complete, failed
    otherwise (with its log and last error line). Polls every ``poll_seconds``, slowing to ``max_poll_seconds``
    while nothing changes: one ``squeue`` every 10 s is light for a controller, and a job's end is seen within
    10 s, not half a minute later.

    Raises:
        StudyError: ``timeout`` seconds passed first.
    """
    plan = submission.plan
    by_label = {job.label: job for job in plan.ordered}
    waiting = {label: job_id for label, job_id in submission.job_of.items() if label in by_label}
    total, count = len(waiting), 0
    finished: list[Job] = []
    failed: list[tuple[Job, str]] = []
    blocked: list[Job] = []
    report_id = submission.report_id
    report_error = submission.report_error
    if report_id is None and not waiting and not submission.report_written and report_error is None:
        report_error = "no report job"
    seen: dict[str, str] = {}
    interval, start, warned = poll_seconds, time.monotonic(), False

    def line(text: str) -> None:
        nonlocal count
        count += 1
        echo(f"[{count}/{total}] {text}")

    while waiting or report_id:
        states, error = query_states()
        changed = False
        if states is None:
            if not warned:
                echo(f"note: cannot ask SLURM ({error}); trying again")
                warned = True
        else:
            for job_id in dict.fromkeys(waiting.values()):
                state = states.get(job_id)
                previous = seen.get(job_id)
                if state is not None:
                    seen[job_id] = state.state
                if state is not None and state.active:
                    if previous in RUNNING_STATES and not state.running:
                        labels = [label for label, jid in waiting.items() if jid == job_id]
                        echo(f"        requeued {', '.join(labels)} (job {job_id}): it continues from its last "
                             "checkpoint")
                        changed = True
                    continue
                changed = True
                for label in [label for label, jid in waiting.items() if jid == job_id]:
                    del waiting[label]
                    job = by_label[label]
                    if directory_state(job.directory) == DONE:
                        job.status = "done"
                        finished.append(job)
                        # drago's own time for the work (SLURM's elapsed time restarts when a job is requeued)
                        seconds = job_wall_time(job) or (_elapsed_s(state.elapsed) if state is not None else None)
                        outcome = job_outcome(job)
                        line(f"done    {label}" + (f" in {format_duration(seconds)}" if seconds is not None else "")
                             + (f": {outcome}" if outcome else ""))
                    elif state is not None and state.state == "CANCELLED" and state.reason == NEVER_SATISFIED:
                        job.status = "blocked"
                        blocked.append(job)
                        line(f"not started: {label} (job {job_id}: its run failed)")
                    else:
                        job.status = "failed"
                        why = failure_reason(plan, job_id, state, job.log)
                        failed.append((job, why))
                        line(f"FAILED  {label} ({why})")
            if report_id and not waiting:
                state = states.get(report_id)
                if state is None or not state.active:
                    changed = True
                    log = plan.out / LOG_FOLDER / "report.log"
                    if state is not None and state.state == "COMPLETED":
                        for name in ("report.html", "report.md"):
                            echo(f"wrote {plan.report_dir / name} (job {report_id})")
                    else:
                        report_error = failure_reason(plan, report_id, state, log)
                        echo(f"report not written: {report_error}")
                    report_id = None
        if not (waiting or report_id):
            break
        if timeout is not None and time.monotonic() - start > timeout:
            raise StudyError(f"gave up waiting after {timeout:.0f} s; the jobs carry on in SLURM")
        interval = poll_seconds if changed else min(max_poll_seconds, interval * 1.5)
        time.sleep(interval)
    return SlurmResult(plan, finished, failed, blocked, report_error)


# ---------------------------------------------------------------------------------------------------
# --status
# ---------------------------------------------------------------------------------------------------
def _local_study_pid(out: Path) -> str | None:
    """The pid of a local ``drago study`` working in ``out`` (it holds the lock), else None."""
    path = Path(out) / LOCK_FILE
    try:
        import fcntl

        with path.open("r") as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                return handle.read().strip() or "?"
            fcntl.flock(handle, fcntl.LOCK_UN)
    except (OSError, ImportError):
        return None
    return None


def status_lines(plan: StudyPlan) -> list[str]:
    """``drago study --status``: every job of the plan as queued, running, done, failed or to do, from SLURM
    (``squeue``, where the study submitted jobs) and from the run directories."""
    record = Record.load(plan.out)
    states: dict[str, SlurmState] = {}
    lines = [f"drago study {plan.preset} in {plan.out}: {len(plan.runs)} run{'s' * (len(plan.runs) != 1)}, "
             f"{len(plan.transfers)} transfer{'s' * (len(plan.transfers) != 1)} and the report"]
    if record.jobs:
        found, error = query_states() if shutil.which("squeue") else (None, "squeue is not on the PATH")
        if found is None:
            lines.append(f"  note: cannot ask SLURM ({error}); states below come from the run directories only")
        else:
            states = found
    pid = _local_study_pid(plan.out)
    if pid:
        lines.append(f"  a local `drago study` is working in this folder (pid {pid})")
    counts = {name: 0 for name in ("done", "running", "queued", "failed", "to do")}
    rows = []
    for job in plan.ordered:
        job_id = record.latest.get(job.label)
        state = states.get(job_id) if job_id else None
        ref = f"job {job_id} " if job_id else ""
        if job.recorded:
            kind, detail = "done", f"recorded in {job.record}"
        elif job.state == DONE:
            seconds = job_wall_time(job)
            kind, detail = "done", f"{ref}" + (f"in {format_duration(seconds)}" if seconds is not None else "")
        elif state is not None and state.active:
            kind = "running" if state.running else "queued"
            detail = f"{ref}{state.describe()}"
        elif state is not None:  # ended without finishing the job's work
            if state.state == "CANCELLED" and state.reason == NEVER_SATISFIED:
                kind, detail = "failed", f"{ref}not started: its run failed"
            else:
                kind, detail = "failed", failure_reason(plan, job_id, state, job.log)
        else:
            kind = "to do"
            detail = "interrupted: resumes from its last checkpoint" if job.state == RESUME else "not started"
            if job_id and states:
                detail = f"{ref}is no longer known to SLURM; {detail}"
            if pid and job.state == RESUME:
                kind, detail = "running", "in the local study"
        counts[kind] += 1
        rows.append((kind, job.label, detail))
    width = max((len(label) for _, label, _ in rows), default=0)
    lines += [f"  {kind:<8} {label:<{width}}  {detail}".rstrip() for kind, label, detail in rows]
    report_id = record.latest.get(REPORT_LABEL)
    report_state = states.get(report_id) if report_id else None
    html = plan.report_dir / "report.html"
    if report_state is not None and report_state.active:
        report = f"job {report_id} {report_state.describe()}"
    elif html.is_file():
        report = f"{html} ({datetime.fromtimestamp(html.stat().st_mtime).strftime('%Y-%m-%d %H:%M')})"
    elif report_id and report_id in record.jobs and states:
        report = failure_reason(plan, report_id, report_state, plan.out / LOG_FOLDER / "report.log")
    else:
        report = "not written yet"
    lines.append(f"  report:  {report}")
    lines.append("  " + ", ".join(f"{n} {name}" for name, n in counts.items()))
    return lines + records_status(plan)
