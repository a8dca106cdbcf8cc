"""``drago study`` as one call: the plan, then what the mode asks of it (run it, describe it, report its state or
write its report), on this machine or through SLURM. The command line parses its arguments into
:func:`study_command` and prints what it returns.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drago.study.local import run_study
from drago.study.plan import (DEFAULT_METHODS, DEFAULT_PRESET, DEFAULT_SEEDS, StudyError, default_study_dir,
                              describe_plan, parse_cases, parse_seeds, plan_study)
from drago.study.report import write_report
from drago.study.slurm.monitoring import active_job_ids, status_lines, wait_study
from drago.study.slurm.options import job_overrides, make_options, require_submitit
from drago.study.slurm.submission import describe_resources, describe_submission, submit_study
from drago.training.run import continue_with
from drago.training.transfer import DEFAULT_EPISODES

__all__ = ["MODES", "SLURM_OPTIONS", "StudyOutcome", "study_command"]

MODES = ("run", "dry-run", "status", "report-only")
BACKENDS = ("local", "slurm")
#: The keywords of ``slurm`` (those of :func:`drago.study.slurm.options.make_options` but ``jobs``), in the order
#: a local study names the first one it was given.
SLURM_OPTIONS = ("partition", "account", "qos", "time", "cpus", "gpus", "jobs_per_gpu", "mem", "sbatch")


@dataclass(frozen=True)
class StudyOutcome:
    """How a study command ended: ``ok``, and its last line (None: nothing more to say); the command line prints
    the line, on stderr after ``drago:`` when not ok, and exits 0 or 1."""

    ok: bool
    message: str | None = None


def study_command(preset: str | None = None, methods: Sequence[str] | None = None,
                  seeds: Sequence[str | int] | None = None, out: str | Path | None = None,
                  overrides: Sequence[str] = (), jobs: int | None = None, transfers: bool = True,
                  transfer_episodes: int | None = None, transfer_eval_every: int = 1,
                  transfer_few_shot_episodes: int | None = None, transfer_reward: str | None = None,
                  cases: Sequence[str] | None = None, records: str | Path | None = None, mode: str = "run",
                  backend: str = "local", wait: bool = False, slurm: Mapping[str, Any] | None = None,
                  echo: Callable[[str], None] = print) -> StudyOutcome:
    """``drago study``: plan the study and do what ``mode`` asks, printing through ``echo``.

    Args:
        preset: Preset of every run (None: ``minigrid-cpu``).
        methods: Continual methods (None: the seven of the grid study).
        seeds: Seeds, or ranges such as ``"1-3"`` (None: 1 2 3).
        out: The study folder (None: ``runs/study/PRESET``).
        overrides: ``key=value`` settings for every run.
        jobs: Local: runs at a time (None: 1); SLURM: the most jobs of the study running at once (None: no cap).
        transfers: Plan the transfer cases of every run.
        transfer_episodes: Learner episodes of each transfer case (None: 20).
        transfer_eval_every: Evaluate each transfer after every this many learner episodes.
        transfer_few_shot_episodes: Read each transfer's few-shot score after this many learner episodes (None: 20,
            or ``transfer_episodes`` if fewer).
        transfer_reward: ``dense`` or ``sparse`` for the transfers' reward (None: each run's default).
        cases: ``TASK:K`` transfer cases instead of the paper's.
        records: The records folder, if units are recorded (see :func:`drago.study.plan.plan_study`).
        mode: ``run`` (the default), ``dry-run`` (the plan, and the sbatch options of every job with SLURM),
            ``status`` (what is queued, running, done and failed) or ``report-only``.
        backend: ``local`` (child processes on this machine) or ``slurm`` (batch jobs, submitted with submitit).
        wait: With SLURM, follow the jobs until they end (the local backend always does).
        slurm: The SLURM options, :func:`drago.study.slurm.options.make_options`'s keywords but ``jobs``
            (:data:`SLURM_OPTIONS`); None or empty values are not given.

    Returns:
        Whether the study did all it was asked, and its last line.

    Raises:
        StudyError: A bad argument (one line naming it), SLURM options without the SLURM backend, a local study
            in a folder whose SLURM jobs are queued or running, or another study working in the folder.
        Interrupted: Ctrl-C while running, submitting or following the jobs (after the local jobs stopped).
        ConfigError: An unknown preset, method or setting.
    """
    if mode not in MODES:
        raise StudyError(f"the mode of a study is one of {', '.join(MODES)}, got '{mode}'")
    if backend not in BACKENDS:
        raise StudyError(f"--backend is local or slurm, got '{backend}'")
    given = {name: value for name, value in (slurm or {}).items() if value not in (None, [], ())}
    unknown = sorted(set(given) - set(SLURM_OPTIONS))
    if unknown:
        raise StudyError(f"unknown SLURM option '{unknown[0]}' (the options: {', '.join(SLURM_OPTIONS)})")
    preset = preset or DEFAULT_PRESET
    overrides = list(overrides)
    on_slurm = backend == "slurm"
    cores, options = None, None
    if on_slurm:
        options = make_options(**given, jobs=jobs)
        if mode not in ("status", "report-only"):
            require_submitit()
        # The jobs run elsewhere: every path they are given is absolute.
        out = Path(out or default_study_dir(preset)).absolute()
        overrides = job_overrides(options, overrides)
        jobs, cores = options.runs_per_job, max(options.cpus, options.runs_per_job)  # threads = CPUs / runs, >= 1
    else:
        first = next((name for name in SLURM_OPTIONS if name in given), None)
        if first is not None:
            raise StudyError(f"--{first.replace('_', '-')} is a SLURM option: add --backend slurm")
        jobs = 1 if jobs is None else jobs
    if records is not None:
        records = Path(records).absolute() if on_slurm else Path(records)
    plan = plan_study(preset, methods or DEFAULT_METHODS, parse_seeds(seeds) if seeds else DEFAULT_SEEDS, out=out,
                      overrides=overrides, jobs=jobs, transfers=transfers,
                      transfer_episodes=DEFAULT_EPISODES if transfer_episodes is None else transfer_episodes,
                      transfer_eval_every=transfer_eval_every, cores=cores, check_settings=mode != "status",
                      transfer_reward=transfer_reward, transfer_few_shot_episodes=transfer_few_shot_episodes,
                      cases=parse_cases(cases) if cases else None, records=records)
    if mode == "status":
        for line in status_lines(plan):
            echo(line)
        return StudyOutcome(True)
    if mode == "report-only":
        _, error = write_report(plan, echo)
        return StudyOutcome(False, f"no report: {error}") if error else StudyOutcome(True)
    resources = describe_resources(options, plan) if on_slurm else None
    for line in describe_plan(plan, verbose=mode == "dry-run", resources=resources):
        echo(line)
    if mode == "dry-run":
        if on_slurm:
            for line in describe_submission(plan, options):
                echo(line)
        return StudyOutcome(True)
    if on_slurm:
        with continue_with("run the same `drago study` command again: it submits what is missing, never a "
                           "job SLURM still has"):
            submission = submit_study(plan, options, echo=echo)
        if submission.report_error:
            return StudyOutcome(False, f"no report: {submission.report_error}")
        if not wait:
            return StudyOutcome(True)
        with continue_with("the jobs carry on in SLURM; the same command with --status shows them"):
            result = wait_study(submission, echo=echo)
    else:
        active = active_job_ids(plan.out)
        if active:
            raise StudyError(f"SLURM jobs of this study are queued or running in {plan.out} (jobs "
                             f"{', '.join(active)}); follow them with --backend slurm --status, or scancel them first")
        with continue_with("run the same `drago study` command again to continue"):
            result = run_study(plan, echo=echo)
    return StudyOutcome(result.ok, result.summary_line())
