"""What every job of a SLURM study asks for: the command line's SLURM options, checked, and submitit."""

from __future__ import annotations

import math
import os
import re
import shlex
import shutil
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from drago.study.plan import StudyError

__all__ = ["SlurmOptions", "import_submitit", "job_overrides", "make_options", "parse_time", "require_commands",
           "require_submitit"]

DEFAULT_TIME_MIN = 60
INSTALL_HINT = "pip install -e '.[slurm]'"
SUBMITIT_LOG_VARIABLE = "SUBMITIT_LOG_LEVEL"  # NOCONFIG: submitit leaves logging alone (see import_submitit)

# sbatch options the study sets itself, or that have a drago flag of their own.
_OWN_FLAGS = {"partition": "--partition", "p": "--partition", "account": "--account", "A": "--account",
              "qos": "--qos", "q": "--qos", "time": "--time", "t": "--time", "cpus-per-task": "--cpus",
              "c": "--cpus", "gpus": "--gpus", "gpus-per-node": "--gpus", "G": "--gpus", "mem": "--mem"}
_STUDY_SETS = {"job-name", "J", "dependency", "d", "output", "o", "error", "e", "open-mode", "signal", "array",
               "a", "wrap", "parsable", "chdir", "D", "requeue", "no-requeue", "kill-on-invalid-dep", "nodes", "N",
               "ntasks", "n", "ntasks-per-node"}


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


def import_submitit() -> Any:
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
        return import_submitit()
    except ImportError:
        raise StudyError(f"--backend slurm needs submitit, which is not installed: {INSTALL_HINT}") from None


def require_commands(*names: str) -> None:
    missing = [name for name in names if shutil.which(name) is None]
    if missing:
        raise StudyError(f"--backend slurm needs SLURM's {', '.join(missing)} on the PATH: run it on a machine "
                         "that submits jobs to the cluster (a login node)")
