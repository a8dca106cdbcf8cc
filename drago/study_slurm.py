"""``drago study --backend slurm``: the study's plan as SLURM batch jobs, submitted with submitit.

The plan is the local backend's (:func:`drago.study.plan.plan_study`): what each job does follows from its directory.
Here every job becomes a SLURM batch job, and the order is SLURM's to keep:

* a run's transfers wait for it (``--dependency=afterok:RUN``), the report job for every job of the study
  (``afterany``); a job whose run failed is cancelled by SLURM (``--kill-on-invalid-dep=yes``) instead of
  waiting forever;
* ``--jobs N`` caps the jobs running at once: the jobs are dealt into N lanes, one SLURM job name each, and
  ``--dependency=singleton`` lets one job of a name run at a time;
* the command returns once the jobs are submitted; the job ids are kept in ``OUT/slurm/jobs.json``.

Each job runs ``python -m drago ARGS`` (:class:`StudyJob`, pickled by submitit), with ``ARGS`` worked out on the
node when the job starts: ``drago train``/``drago transfer`` in an empty directory, ``drago resume DIR`` in an
interrupted one, nothing in a finished one. Its output is appended to ``OUT/logs/`` as with the local backend.
SLURM signals a job (USR2) shortly before its time limit; submitit then calls :meth:`StudyJob.checkpoint`,
which stops drago (SIGTERM, as Ctrl-C) and has the job requeued under the same id; the requeued job
resumes from the run's last checkpoint. A preempted or cancelled job, or one whose node failed, is continued the
same way by running the study command again.

Job states come from ``squeue -t all`` and from the run directories, never from ``sacct``: without the
accounting daemon (slurmdbd) there is no ``sacct``, and submitit reports every state as UNKNOWN. ``squeue``
lists finished jobs for ``MinJobAge`` seconds (300 by default); after that the run directories, which say
exactly what is finished, are the only record needed.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from drago.study.local import LOCK_FILE, PARENT_ENV, study_lock
from drago.study.plan import (DONE, LOG_FOLDER, RESUME, START, Job, StudyError, StudyPlan, directory_state,
                              format_duration, job_outcome, job_wall_time, records_status, summary_line, transfer_argv)
from drago.study.report import write_report
from drago.training.rundir import CHECKPOINT_FOLDER, SUMMARY_FILE, atomic_write_text

__all__ = ["SlurmOptions", "SlurmResult", "StudyJob", "Submission", "active_job_ids", "describe_resources",
           "describe_submission", "job_overrides", "make_options", "parse_time", "require_submitit", "status_lines",
           "submit_study", "wait_study"]

SLURM_FOLDER = "slurm"  # OUT/slurm: jobs.json, shared.json, submitit/ (scripts, pickles, SLURM's own logs)
JOBS_FILE = "jobs.json"
SHARED_FILE = "shared.json"
SUBMITIT_FOLDER = "submitit"
PROBE_FOLDER = "check"
REPORT_LABEL = "report"
DEFAULT_TIME_MIN = 60
PROBE_WAIT_S = 60.0  # how long the study command waits for its shared-folder check job before going on
MAX_TIMEOUT_REQUEUES = 100  # submitit's bound on requeues after time limits; progress is checked each time
STOP_CHILD_S = 20.0  # how long a stopped drago may take to exit before it is killed
INSTALL_HINT = "pip install -e '.[slurm]'"
SUBMITIT_LOG_VARIABLE = "SUBMITIT_LOG_LEVEL"  # NOCONFIG: submitit leaves logging alone (see _import_submitit)

# squeue's job states (man squeue, JOB STATE CODES). A job is "active" until it ends; requeued jobs are active.
RUNNING_STATES = frozenset({"RUNNING", "COMPLETING", "CONFIGURING", "SIGNALING", "STAGE_OUT", "RESIZING"})
QUEUED_STATES = frozenset({"PENDING", "REQUEUED", "REQUEUE_FED", "REQUEUE_HOLD", "SPECIAL_EXIT", "SUSPENDED",
                           "STOPPED", "RESV_DEL_HOLD", "POWER_UP_NODE"})
ACTIVE_STATES = RUNNING_STATES | QUEUED_STATES
NEVER_SATISFIED = "DependencyNeverSatisfied"

# sbatch options the study sets itself, or that have a drago flag of their own.
_OWN_FLAGS = {"partition": "--partition", "p": "--partition", "account": "--account", "A": "--account",
              "qos": "--qos", "q": "--qos", "time": "--time", "t": "--time", "cpus-per-task": "--cpus",
              "c": "--cpus", "gpus": "--gpus", "gpus-per-node": "--gpus", "G": "--gpus", "mem": "--mem"}
_STUDY_SETS = {"job-name", "J", "dependency", "d", "output", "o", "error", "e", "open-mode", "signal", "array",
               "a", "wrap", "parsable", "chdir", "D", "requeue", "no-requeue", "kill-on-invalid-dep", "nodes", "N",
               "ntasks", "n", "ntasks-per-node"}
# Extra sbatch options the shared-folder check job does not take: it must start now and needs next to nothing.
_NOT_FOR_CHECK = ("begin", "hold", "gres", "gpus-per-task", "cpus-per-gpu", "mem-per-cpu", "mem-per-gpu",
                  "time-min", "mail-type", "mail-user", "exclusive", "deadline", "nice", "priority")


# ---------------------------------------------------------------------------------------------------
# options
# ---------------------------------------------------------------------------------------------------
@dataclass
class SlurmOptions:
    """What every job of a SLURM study asks for.

    Attributes:
        partition, account, qos: Passed to sbatch when set (None: the cluster's default).
        time_min: Time limit of each job in minutes; a job near it is requeued and resumes.
        cpus: CPUs per job (``--cpus-per-task``); new runs get ``train.threads`` = cpus // runs per job.
        gpus: GPUs per job (``--gpus-per-node``); with GPUs the runs get ``train.device=cuda``.
        mem: Memory per job, SLURM's syntax (``16G``); None: the partition's default.
        extra: Further sbatch options, ``{"constraint": "a100"}`` (True for a flag without value).
        max_running: The most SLURM jobs of the study running at once (None: no cap).
        jobs_per_gpu: Runs sharing one GPU; a job with G GPUs then runs G x this many runs side by side.
    """

    partition: str | None = None
    account: str | None = None
    qos: str | None = None
    time_min: int = DEFAULT_TIME_MIN
    cpus: int = 1
    gpus: int = 0
    mem: str | None = None
    extra: dict[str, str | bool] = field(default_factory=dict)
    max_running: int | None = None
    jobs_per_gpu: int = 1

    @property
    def runs_per_job(self) -> int:
        return self.gpus * self.jobs_per_gpu if self.gpus else 1

    @property
    def signal_delay_s(self) -> int:
        """Seconds before the time limit at which SLURM sends USR2 (submitit's requeue signal)."""
        return max(10, min(90, self.time_min * 60 // 4))


def parse_time(text: str) -> int:
    """A SLURM time limit (``MIN``, ``MIN:SEC``, ``H:MIN:SEC``, ``D-H``, ``D-H:MIN``, ``D-H:MIN:SEC``) in whole minutes.

    Raises:
        StudyError: anything else, or less than a minute.
    """
    match = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", str(text).strip())
    if not match:
        raise StudyError(f"--time takes minutes or SLURM's [D-]HH:MM:SS, got '{text}'")
    days, a, b, c = (int(x) if x is not None else None for x in match.groups())
    if days is not None:  # D-H[:M[:S]]
        seconds = days * 86400 + a * 3600 + (b or 0) * 60 + (c or 0)
    elif c is not None:  # H:M:S
        seconds = a * 3600 + b * 60 + c
    else:  # M[:S]
        seconds = a * 60 + (b or 0)
    if seconds < 60:
        raise StudyError(f"--time must be at least a minute (SLURM's shortest limit), got '{text}'")
    return math.ceil(seconds / 60)


def _parse_mem(text: str) -> str:
    match = re.fullmatch(r"(\d+)\s*([KMGTkmgt]?)[Bb]?", str(text).strip())
    if not match or int(match.group(1)) <= 0:
        raise StudyError(f"--mem takes a size like 16G or 500M (SLURM's syntax), got '{text}'")
    return match.group(1) + match.group(2).upper()


def _parse_sbatch(items: Iterable[str]) -> dict[str, str | bool]:
    options: dict[str, str | bool] = {}
    for item in items:
        try:
            tokens = shlex.split(item)
        except ValueError as err:
            raise StudyError(f"--sbatch: cannot read '{item}' ({err})") from None
        i = 0
        while i < len(tokens):
            token = tokens[i]
            if not re.fullmatch(r"--[A-Za-z][A-Za-z0-9-]*(=.*)?", token, flags=re.DOTALL):
                raise StudyError(f"--sbatch takes long sbatch options such as --constraint=a100, got '{token}'")
            key, sep, value = token[2:].partition("=")
            if not sep and i + 1 < len(tokens) and not tokens[i + 1].startswith("-"):
                value, sep = tokens[i + 1], "="
                i += 1
            if key in _OWN_FLAGS:
                raise StudyError(f"--sbatch cannot set --{key}: use drago study's {_OWN_FLAGS[key]}")
            if key in _STUDY_SETS:
                raise StudyError(f"--sbatch cannot set --{key}: the study sets it for each job")
            options[key] = value if sep else True
            i += 1
    return options


def make_options(partition: str | None = None, account: str | None = None, qos: str | None = None,
                 time: str | int | None = None, cpus: int | None = None, gpus: int | None = None,
                 mem: str | None = None, sbatch: Sequence[str] = (), jobs: int | None = None,
                 jobs_per_gpu: int | None = None) -> SlurmOptions:
    """Checked :class:`SlurmOptions` from the command line's values (None: the default).

    Raises:
        StudyError: a bad value, named in one line.
    """
    for flag, value in (("--partition", partition), ("--account", account), ("--qos", qos)):
        if value is not None and (not value.strip() or any(ch.isspace() for ch in value)):
            raise StudyError(f"{flag} takes one name, got '{value}'")
    for flag, value, low in (("--cpus", cpus, 1), ("--gpus", gpus, 0), ("--jobs", jobs, 1),
                             ("--jobs-per-gpu", jobs_per_gpu, 1)):
        if value is not None and value < low:
            kind = "positive" if low else "non-negative"
            raise StudyError(f"{flag} must be a {kind} integer, got {value}")
    if jobs_per_gpu is not None and not gpus:
        raise StudyError("--jobs-per-gpu shares a GPU between runs: it needs --gpus 1 or more")
    return SlurmOptions(partition=partition, account=account, qos=qos,
                        time_min=DEFAULT_TIME_MIN if time is None else parse_time(str(time)),
                        cpus=cpus or 1, gpus=gpus or 0, mem=None if mem is None else _parse_mem(mem),
                        extra=_parse_sbatch(sbatch), max_running=jobs, jobs_per_gpu=jobs_per_gpu or 1)


def job_overrides(options: SlurmOptions, overrides: Sequence[str]) -> list[str]:
    """The study's overrides for SLURM jobs: ``train.device=cuda`` when the jobs get GPUs and no device is set."""
    overrides = list(overrides)
    if options.gpus and not any(o.partition("=")[0].strip() in ("train.device", "device") for o in overrides):
        overrides.append("train.device=cuda")
    return overrides


def _import_submitit() -> Any:
    """Import submitit without letting it reconfigure the process's logging.

    On import, submitit runs ``logging.config.dictConfig``, which closes every logging handler that exists, the
    caller's own included (a file handler of the user's script; absl's handler, which then closes the stream it was
    given, such as a test runner's captured stderr). ``SUBMITIT_LOG_LEVEL=NOCONFIG`` skips that. It is set only
    for the import: jobs inherit the submitting environment, and on the nodes submitit's own log lines are wanted.
    """
    if sys.modules.get("submitit") is not None:
        return sys.modules["submitit"]
    previous = os.environ.get(SUBMITIT_LOG_VARIABLE)
    os.environ[SUBMITIT_LOG_VARIABLE] = "NOCONFIG"
    try:
        import submitit
    finally:
        if previous is None:
            os.environ.pop(SUBMITIT_LOG_VARIABLE, None)
        else:
            os.environ[SUBMITIT_LOG_VARIABLE] = previous
    return submitit


def require_submitit() -> Any:
    """The submitit module, or a one-line StudyError saying how to install it."""
    try:
        return _import_submitit()
    except ImportError:
        raise StudyError(f"--backend slurm needs submitit, which is not installed: {INSTALL_HINT}") from None


def _require_commands(*names: str) -> None:
    missing = [name for name in names if shutil.which(name) is None]
    if missing:
        raise StudyError(f"--backend slurm needs SLURM's {', '.join(missing)} on the PATH: run it on a machine "
                         "that submits jobs to the cluster (a login node)")


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


def _sbatch_error(text: str) -> str:
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    errors = [line for line in lines if "error" in line.lower()] or lines or ["sbatch failed"]
    return re.sub(r"^sbatch: error: ", "", errors[-1])


def _scancel(job_ids: Iterable[str]) -> None:
    ids = list(job_ids)
    if ids:
        subprocess.run(["scancel", *ids], check=False, capture_output=True, text=True, timeout=60,
                              stdin=subprocess.DEVNULL)


# ---------------------------------------------------------------------------------------------------
# what a job runs on its node
# ---------------------------------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------------------------------
# the SLURM jobs of a plan
# ---------------------------------------------------------------------------------------------------
@dataclass(eq=False)
class Unit:
    """One SLURM job of the study: one drago job, several runs sharing GPUs, or the report."""

    kind: str  # run, transfer or report
    members: list[Job]
    after: list[Unit | str] = field(default_factory=list)  # afterok (afterany for the report): units or job ids
    number: int = 0  # 1-based, in submission order (the dry run's names)
    job_id: str | None = None
    name: str = ""

    @property
    def labels(self) -> list[str]:
        return [m.label for m in self.members] or [REPORT_LABEL]

    @property
    def label(self) -> str:
        return " + ".join(self.labels)


def _chunks(items: Sequence[Job], size: int) -> list[list[Job]]:
    return [list(items[i:i + size]) for i in range(0, len(items), size)]


def plan_units(plan: StudyPlan, options: SlurmOptions, kept: dict[str, str] | None = None) -> list[Unit]:
    """The SLURM jobs still to submit for ``plan`` (``kept``: labels whose job is still queued or running),
    runs first, then transfers, then the report; numbered in that order."""
    kept = kept or {}
    size = options.runs_per_job
    runs = [j for j in plan.runs if j.state != DONE and j.label not in kept]
    units = [Unit("run", chunk) for chunk in _chunks(runs, size)]
    unit_of = {job.label: unit for unit in units for job in unit.members}
    groups: dict[Any, tuple[Unit | str | None, list[Job]]] = {}
    for job in plan.transfers:
        if job.state == DONE or job.label in kept:
            continue
        source = job.source
        if source is not None and source.label in unit_of:
            dep: Unit | str | None = unit_of[source.label]
        elif source is not None and source.label in kept:
            dep = kept[source.label]
        else:
            dep = None  # its run was finished when the plan was made
        key = id(dep) if isinstance(dep, Unit) else dep
        groups.setdefault(key, (dep, []))[1].append(job)
    for dep, jobs in groups.values():
        units += [Unit("transfer", chunk, after=[dep] if dep is not None else []) for chunk in _chunks(jobs, size)]
    for number, unit in enumerate(units, 1):
        unit.number = number
    return units


def study_tag(out: Path) -> str:
    return hashlib.sha1(str(Path(out).absolute()).encode()).hexdigest()[:6]


def _job_name(unit: Unit, options: SlurmOptions, out: Path, lane: int | None) -> str:
    if lane is not None:  # --jobs N: one name per lane, and singleton runs one job of a name at a time
        return f"drago-{study_tag(out)}-lane{lane}"
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", unit.labels[0]).strip("-")
    return f"drago-{slug}" + (f"-and-{len(unit.labels) - 1}" if len(unit.labels) > 1 else "")


def _members(unit: Unit, plan: StudyPlan, options: SlurmOptions) -> list[Member]:
    if unit.kind == REPORT_LABEL:
        return [Member(REPORT_LABEL, REPORT_LABEL, str(plan.report_dir), report_argv(plan),
                       str(plan.out / LOG_FOLDER / "report.log"), 1)]
    members = []
    for job in unit.members:
        start = job.argv if job.state == START else _start_argv(job, plan)
        members.append(Member(job.label, job.kind, str(job.directory), start, str(job.log), job.threads))
    return members


def _start_argv(job: Job, plan: StudyPlan) -> list[str]:
    """The command that starts ``job`` from nothing (a job planned as resume may find its directory gone)."""
    if job.kind == "run":
        return ["train", plan.preset, "--method", job.method, "--seed", str(job.seed), "--out", str(job.directory),
                "--no-progress", *plan.overrides_of(job.method)]
    task, after = job.case or ("", 0)
    return transfer_argv(job.directory.parent.parent, task, after, plan)


def report_argv(plan: StudyPlan) -> list[str]:
    """``drago study ... --report-only``: the report job's command, the study's own arguments."""
    argv = ["study", plan.preset, "--methods", *plan.methods, "--seeds", *map(str, plan.seeds), "--out",
            str(plan.out), "--transfer-episodes", str(plan.transfer_episodes), "--transfer-eval-every",
            str(plan.transfer_eval_every)]
    if plan.transfer_reward:
        argv += ["--transfer-reward", plan.transfer_reward]
    if plan.transfer_few_shot_episodes is not None:
        argv += ["--transfer-few-shot-episodes", str(plan.transfer_few_shot_episodes)]
    if plan.own_cases:
        argv += ["--cases", *(f"{task}:{after}" for task, after in plan.cases)]
    if not plan.cases:
        argv.append("--no-transfer")
    if plan.records is not None:
        argv += ["--records", str(plan.records)]
    return [*argv, "--report-only", *plan.overrides]


def _parameters(unit: Unit, options: SlurmOptions, out: Path, name: str, dependency: str | None) -> dict[str, Any]:
    """submitit's SlurmExecutor parameters (sbatch options) of one job."""
    extra: dict[str, Any] = {"requeue": True, "kill-on-invalid-dep": "yes", "chdir": str(out)}
    if options.mem:
        extra["mem"] = options.mem
    extra.update(options.extra)
    report = unit.kind == REPORT_LABEL
    params: dict[str, Any] = {"job_name": name, "time": options.time_min, "nodes": 1, "ntasks_per_node": 1,
                              "cpus_per_task": 1 if report else options.cpus,
                              "signal_delay_s": options.signal_delay_s, "additional_parameters": extra}
    for key, value in (("partition", options.partition), ("account", options.account), ("qos", options.qos)):
        if value:
            params[key] = value
    if options.gpus and not report:
        params["gpus_per_node"] = options.gpus
    if dependency:
        params["dependency"] = dependency
    return params


def _dependency(unit: Unit, ids: Callable[[Unit | str], str], check: str | None, singleton: bool) -> str | None:
    parts = []
    after = [ids(dep) for dep in unit.after]
    if unit.kind == REPORT_LABEL:
        if after:
            parts.append("afterany:" + ":".join(after))
    else:
        after += [check] if check else []
        if after:
            parts.append("afterok:" + ":".join(after))
    if singleton and unit.kind != REPORT_LABEL:
        parts.append("singleton")
    return ",".join(parts) or None


def _sbatch_flags(params: dict[str, Any], folder: Path) -> list[str]:
    """The ``#SBATCH`` options submitit writes for ``params`` (its own script text, where it can)."""
    try:
        _import_submitit()
        from submitit.slurm.slurm import _make_sbatch_string

        text = _make_sbatch_string(command="true", folder=folder, **params)
        return [line[len("#SBATCH "):] for line in text.splitlines() if line.startswith("#SBATCH ")]
    except Exception:  # another submitit version: our own rendering of the same parameters
        flags = []
        for key, value in {**{k: v for k, v in params.items() if k != "additional_parameters"},
                           **params.get("additional_parameters", {})}.items():
            key = {"time": "time", "signal_delay_s": "signal"}.get(key, key).replace("_", "-")
            value = f"USR2@{value}" if key == "signal" else value
            flags.append(f"--{key}" if value is True else f"--{key}={shlex.quote(str(value))}")
        return sorted(flags)


def _lanes(options: SlurmOptions) -> Callable[[Unit], int | None]:
    count = {"next": 0}

    def lane(unit: Unit) -> int | None:
        if options.max_running is None or unit.kind == REPORT_LABEL:
            return None
        value = count["next"] % options.max_running
        count["next"] += 1
        return value

    return lane


def describe_resources(options: SlurmOptions, plan: StudyPlan) -> list[str]:
    """The plan's lines on SLURM jobs (in place of the local backend's jobs and cores)."""
    where = ", ".join(f"{name} {value}" for name, value in (("partition", options.partition),
                      ("account", options.account), ("QoS", options.qos)) if value) or "the cluster's default partition"
    gpus = (f"{options.gpus} GPU{'s' * (options.gpus != 1)}" if options.gpus else "no GPU")
    share = ""
    if options.gpus:
        share = (f", {options.jobs_per_gpu} runs per GPU" if options.jobs_per_gpu > 1 else ", a GPU per run") + \
                " (train.device=cuda)"
    runs = options.runs_per_job
    lines = [f"  slurm:     {where}; each job {options.time_min} min, {options.cpus} CPU{'s' * (options.cpus != 1)}, "
             f"{gpus}{share}, memory {options.mem or 'as the partition gives'}"
             + (f"; {runs} runs per job" if runs > 1 else ""),
             "  jobs:      " + (f"at most {options.max_running} running at once (--jobs)" if options.max_running
                                 else "all submitted at once, SLURM decides how many run") +
             f"; new runs with train.threads={plan.threads}; output in {plan.out / LOG_FOLDER}/, SLURM's in "
             f"{slurm_dir(plan.out) / SUBMITIT_FOLDER}/"]
    checkpoint = _checkpoint_freq(plan)
    if checkpoint:
        lines.append(f"  requeue:   a job near its time limit or preempted is requeued and resumes from its last "
                     f"checkpoint (every {checkpoint} env steps, train.checkpoint_freq)")
    if options.extra:
        lines.append("  sbatch:    " + " ".join(f"--{k}" if v is True else f"--{k}={v}"
                                                for k, v in options.extra.items()))
    return lines


def _checkpoint_freq(plan: StudyPlan) -> int | None:
    from drago.config import ConfigError, load_config

    try:
        cfg = load_config(plan.preset, plan.overrides_of(plan.methods[0]), method=plan.methods[0], seed=plan.seeds[0])
        return cfg.train.checkpoint_freq
    except ConfigError:
        return None


def describe_submission(plan: StudyPlan, options: SlurmOptions) -> list[str]:
    """``--dry-run``: the sbatch options of every job that would be submitted (``JOBn``: job n's id)."""
    record = Record.load(plan.out)
    kept: dict[str, str] = {}
    lines: list[str] = []
    if record.latest:
        states, error = query_states()
        if states is None:
            lines.append(f"  note:      cannot ask SLURM which of the study's jobs are still queued ({error}): "
                         "listed as if none were")
        else:
            kept, _ = _reconcile(plan, record, states)
            for job_id in dict.fromkeys(kept.values()):
                labels = ", ".join(record.jobs.get(job_id, {}).get("labels", []))
                lines.append(f"  kept:      job {job_id} ({states[job_id].describe()}): {labels}")
    units = plan_units(plan, options, kept)
    if not units and not kept:
        return [*lines, "  nothing to submit: every job is finished; the study writes the report here"]
    report = Unit(REPORT_LABEL, [], after=[*units, *dict.fromkeys(kept.values())], number=len(units) + 1)
    lane = _lanes(options)
    folder = slurm_dir(plan.out) / SUBMITIT_FOLDER
    for unit in [*units, report]:
        name = _job_name(unit, options, plan.out, lane(unit))
        dependency = _dependency(unit, lambda dep: f"JOB{dep.number}" if isinstance(dep, Unit) else dep, None,
                                 options.max_running is not None)
        flags = _sbatch_flags(_parameters(unit, options, plan.out, name, dependency), folder)
        lines.append(f"  JOB{unit.number}: {unit.label}")
        lines.append(f"    sbatch {' '.join(flags)}")
        for member in _members(unit, plan, options):
            lines.append(f"    runs: python -m drago {' '.join(member.argv_now() or ['(nothing: complete)'])}")
    check = "" if (slurm_dir(plan.out) / SHARED_FILE).is_file() else \
        "; first a one-minute job checks that the nodes see the study folder"
    lines.append(f"  ({len(units) + 1} SLURM job{'s' * (len(units) != 0)}; JOBn stands for the id SLURM gives "
                 f"job n{check})")
    return lines


# ---------------------------------------------------------------------------------------------------
# submitting
# ---------------------------------------------------------------------------------------------------
@dataclass
class Submission:
    """What ``submit_study`` left in the queue: the SLURM job of every unfinished label, and the report's."""

    plan: StudyPlan
    job_of: dict[str, str]  # label -> job id, for every job of the plan that is not finished
    report_id: str | None
    submitted: list[Unit]
    kept: dict[str, str]
    report_written: list[Path] = field(default_factory=list)
    report_error: str | None = None


def _check_writable(out: Path) -> None:
    try:
        folder = slurm_dir(out)
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-check-{uuid.uuid4().hex}"
        probe.write_text("drago\n")
        probe.unlink()
    except OSError as err:
        raise StudyError(f"cannot write to the study folder {out} ({err.strerror or err}); choose an --out this "
                         "machine and the SLURM nodes can both write") from None


def _reconcile(plan: StudyPlan, record: Record, states: dict[str, SlurmState]) -> tuple[dict[str, str], list[str]]:
    """The labels whose job SLURM still has (kept), and queued jobs to cancel: those waiting for a job that
    failed or is gone, which would never start."""
    labels_of: dict[str, list[str]] = {}
    for job in plan.ordered:
        job_id = record.latest.get(job.label)
        if job.state != DONE and job_id and job_id in states and states[job_id].active:
            labels_of.setdefault(job_id, []).append(job.label)
    finished_labels = {j.label for j in plan.ordered if j.state == DONE}
    cancel: list[str] = []

    def satisfiable(dep: str) -> bool:
        if dep in labels_of:
            return True
        state = states.get(dep)
        if state is not None:
            return state.state == "COMPLETED"
        # No longer known to SLURM: fine if what it ran is finished.
        return all(label in finished_labels for label in record.jobs.get(dep, {}).get("labels", []))

    changed = True
    while changed:
        changed = False
        for job_id in list(labels_of):
            if states[job_id].running:
                continue
            after = record.jobs.get(job_id, {}).get("after", [])
            if not all(satisfiable(dep) for dep in after):
                cancel.append(job_id)
                del labels_of[job_id]
                changed = True
    kept = {label: job_id for job_id, labels in labels_of.items() for label in labels}
    return kept, cancel


def _check_shared(plan: StudyPlan, options: SlurmOptions, record: Record, states: dict[str, SlurmState],
                  echo: Callable[[str], None]) -> str | None:
    """Make sure the nodes see the study folder: a one-minute job checks for a file written here.

    Returns the check job's id when it is still queued after :data:`PROBE_WAIT_S` (the study's jobs then wait
    for it), None once the folder is known to be shared.

    Raises:
        StudyError: the check job failed (the nodes do not see the folder) or SLURM refused it.
    """
    shared = slurm_dir(plan.out) / SHARED_FILE
    if shared.is_file():
        return None
    folder = slurm_dir(plan.out) / PROBE_FOLDER
    job_id = record.check
    if job_id and (job_id not in states or not states[job_id].active):
        if job_id in states and states[job_id].state == "COMPLETED":
            _shared_ok(plan.out, job_id, states[job_id].node)
            record.check = None
            return None
        record.check = job_id = None  # failed, cancelled or forgotten: check again
    if job_id is None:
        folder.mkdir(parents=True, exist_ok=True)
        token = uuid.uuid4().hex[:12]
        here, there = folder / f"{token}.here", folder / f"{token}.node"
        here.write_text(f"written by {socket.gethostname()} for the nodes to find\n")
        script = f"test -e {shlex.quote(str(here))} && hostname > {shlex.quote(str(there))}"
        cmd = ["sbatch", "--parsable", "--job-name=drago-check-folder", "--time=1", "--nodes=1", "--ntasks=1",
               "--cpus-per-task=1", "--output=/dev/null", "--error=/dev/null"]
        cmd += [f"--{k}={v}" for k, v in (("partition", options.partition), ("account", options.account),
                                          ("qos", options.qos)) if v]
        cmd += [f"--{k}" if v is True else f"--{k}={v}" for k, v in options.extra.items() if k not in _NOT_FOR_CHECK]
        cmd += ["--wrap", script]
        try:
            proc = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=120,
                                  stdin=subprocess.DEVNULL)
        except (OSError, subprocess.SubprocessError) as err:
            raise StudyError(f"cannot submit to SLURM: {err}") from None
        if proc.returncode != 0:
            raise StudyError(f"SLURM refused the study's jobs: {_sbatch_error(proc.stderr or proc.stdout)}")
        job_id = proc.stdout.strip().split(";")[0]
        record.check = job_id
        record.save()
        echo(f"checking that the SLURM nodes see {plan.out}: job {job_id}")
    deadline = time.monotonic() + PROBE_WAIT_S
    while True:
        now, error = query_states()
        state = (now or {}).get(job_id)
        if state is not None and not state.active:
            if state.state == "COMPLETED":
                node = state.node
                with contextlib.suppress(OSError):
                    node = next(folder.glob("*.node")).read_text().strip() or node
                _shared_ok(plan.out, job_id, node)
                record.check = None
                record.save()
                echo(f"checked: the nodes see the study folder (job {job_id} on {node or 'a node'})")
                return None
            record.check = None
            record.save()
            if state.state == "FAILED":
                raise StudyError(f"the SLURM nodes cannot use the study folder {plan.out}: a check job (job {job_id}"
                                 f"{' on ' + state.node if state.node and not state.node.startswith('(') else ''}) "
                                 "did not find a file written there from this machine, or could not write one; "
                                 "put --out on a filesystem the nodes share (a home or shared scratch folder, not "
                                 "/tmp or a local disk)")
            raise StudyError(f"the job checking that the nodes see {plan.out} (job {job_id}) ended {state.state}; "
                             "run the same command again")
        if time.monotonic() > deadline:
            echo(f"note: the check job {job_id} is still {state.describe() if state else 'queued'}; the study's jobs "
                 "wait for it and SLURM cancels them if the nodes cannot see the study folder")
            return job_id
        if now is None:
            raise StudyError(f"cannot ask SLURM about job {job_id}: {error}")
        time.sleep(1.0)


def _shared_ok(out: Path, job_id: str, node: str) -> None:
    atomic_write_text(slurm_dir(out) / SHARED_FILE, json.dumps(
        {"checked": datetime.now().isoformat(timespec="seconds"), "job": job_id, "node": node}) + "\n")
    with contextlib.suppress(OSError):
        shutil.rmtree(slurm_dir(out) / PROBE_FOLDER)


def submit_study(plan: StudyPlan, options: SlurmOptions, echo: Callable[[str], None] = print) -> Submission:
    """Submit every unfinished job of ``plan`` that SLURM does not already have, then the report job.

    Jobs still queued or running are kept (their ids are in ``OUT/slurm/jobs.json``); queued jobs that wait
    for a job that failed are cancelled and submitted again. With nothing left to run, the report is written
    here and nothing is submitted.

    Raises:
        StudyError: submitit or SLURM's commands missing, a study folder this machine or the nodes cannot
            write, SLURM refusing a job (its message), or another study command working in the folder.
    """
    submitit = require_submitit()
    _require_commands("sbatch", "squeue", "scancel")
    _check_writable(plan.out)
    with study_lock(plan.out):
        record = Record.load(plan.out)
        states, error = query_states()
        if states is None:
            raise StudyError(f"cannot ask SLURM what is queued: {error}")
        kept, cancel = _reconcile(plan, record, states)
        if cancel:
            _scancel(cancel)
            for job_id in cancel:
                echo(f"cancelled job {job_id} ({', '.join(record.jobs.get(job_id, {}).get('labels', []))}): it waited "
                     "for a job that failed or is gone; submitted again")
        units = plan_units(plan, options, kept)
        for job_id in dict.fromkeys(kept.values()):
            labels = ", ".join(record.jobs.get(job_id, {}).get("labels", []))
            echo(f"kept job {job_id} ({states[job_id].describe()}): {labels}")
        ended = {}  # why work submitted before is submitted again
        for job in (job for unit in units for job in unit.members):
            job_id = record.latest.get(job.label)
            if job_id and job_id not in cancel and job_id not in ended:
                ended[job_id] = job
        for job_id, job in ended.items():
            echo(f"again: {job.label} ({_failure(plan, job_id, states.get(job_id), job.log)})")
        report_id = record.latest.get(REPORT_LABEL)
        report_state = states.get(report_id) if report_id else None
        report_active = report_state is not None and report_state.active
        submission = Submission(plan, dict(kept), None, units, kept)
        if not units and not kept:
            if report_active:
                submission.report_id = report_id
                echo(f"kept job {report_id} ({report_state.describe()}): {REPORT_LABEL}")
                return submission
            echo("every job is finished: writing the report here")
            submission.report_written, submission.report_error = write_report(plan, echo)
            return submission
        if not units and not cancel and report_active:
            submission.report_id = report_id
            echo(f"kept job {report_id} ({report_state.describe()}): {REPORT_LABEL}")
            echo(f"nothing new to submit: SLURM has every unfinished job of the study "
                 f"({len(set(kept.values())) + 1} jobs queued or running)")
            return submission
        check = _check_shared(plan, options, record, states, echo) if units else None
        if report_active and report_state is not None and not report_state.running:
            _scancel([report_id])  # a new report job waits for the new jobs too
        folder = slurm_dir(plan.out) / SUBMITIT_FOLDER
        executor = submitit.SlurmExecutor(folder=folder, max_num_timeout=MAX_TIMEOUT_REQUEUES)
        report = Unit(REPORT_LABEL, [], after=[*units, *dict.fromkeys(kept.values())])
        lane = _lanes(options)
        for unit in [*units, report]:
            name = _job_name(unit, options, plan.out, lane(unit))
            after_ids = [dep.job_id if isinstance(dep, Unit) else dep for dep in unit.after]
            dependency = _dependency(unit, lambda dep: dep.job_id if isinstance(dep, Unit) else dep,
                                     check if unit.kind != REPORT_LABEL else None, options.max_running is not None)
            members = _members(unit, plan, options)
            function = StudyJob(members, gpus=0 if unit.kind == REPORT_LABEL else options.gpus,
                                jobs_per_gpu=options.jobs_per_gpu, time_limit_s=options.time_min * 60)
            executor.update_parameters(**_parameters(unit, options, plan.out, name, dependency))
            try:
                with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
                    job = executor.submit(function)
            except Exception as err:  # sbatch's refusal (submitit's FailedJobError) or a missing sbatch
                done = f" ({len([u for u in units if u.job_id])} jobs submitted before it stay queued)" \
                    if any(u.job_id for u in units) else ""
                raise StudyError(f"SLURM refused job {unit.label}: {_sbatch_error(str(err))}{done}") from None
            unit.job_id = str(job.job_id)
            record.add(unit.job_id, unit.labels, unit.kind, [a for a in after_ids if a], name,
                       members[0].argv_now() or [] if members else [])
            record.save()
            first = members[0].argv_now() if members else None
            waits = (f" after job{'s' * (len(after_ids) != 1)} {', '.join(a for a in after_ids if a)}"
                     if after_ids else "")
            echo(f"submitted job {unit.job_id}: {unit.label}{waits}"
                 + (f" (drago {' '.join(first[:2])} ...)" if first and unit.kind != REPORT_LABEL else ""))
            if unit.kind != REPORT_LABEL:
                for label in unit.labels:
                    submission.job_of[label] = unit.job_id
        submission.report_id = report.job_id
        echo(f"{len(units) + 1} SLURM job{'s' * (len(units) != 0)} submitted"
             + (f", {len(set(kept.values()))} kept in the queue" if kept else "")
             + "; the same command with --status shows where they are, with --wait follows them")
        return submission


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


def _failure(plan: StudyPlan, job_id: str, state: SlurmState | None, log: Path) -> str:
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
                        why = _failure(plan, job_id, state, job.log)
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
                        report_error = _failure(plan, report_id, state, log)
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
                kind, detail = "failed", _failure(plan, job_id, state, job.log)
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
        report = _failure(plan, report_id, report_state, plan.out / LOG_FOLDER / "report.log")
    else:
        report = "not written yet"
    lines.append(f"  report:  {report}")
    lines.append("  " + ", ".join(f"{n} {name}" for name, n in counts.items()))
    return lines + records_status(plan)
