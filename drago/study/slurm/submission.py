"""The SLURM jobs of a study's plan: runs, transfers and the report as units of one or more drago jobs, their
sbatch parameters and dependencies, the dry run's description, and their submission with submitit."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import re
import shlex
import shutil
import socket
import subprocess
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from drago.study.local import study_lock
from drago.study.plan import DONE, LOG_FOLDER, START, Job, StudyError, StudyPlan, transfer_argv
from drago.study.report import write_report
from drago.study.slurm.monitoring import SUBMITIT_FOLDER, Record, SlurmState, failure_reason, query_states, slurm_dir
from drago.study.slurm.node import REPORT_LABEL, Member, StudyJob
from drago.study.slurm.options import SlurmOptions, import_submitit, require_commands, require_submitit
from drago.training.rundir import atomic_write_text

__all__ = ["Submission", "Unit", "describe_resources", "describe_submission", "plan_units", "report_argv",
           "submit_study"]

SHARED_FILE = "shared.json"
PROBE_FOLDER = "check"
PROBE_WAIT_S = 60.0  # how long the study command waits for its shared-folder check job before going on
MAX_TIMEOUT_REQUEUES = 100  # submitit's bound on requeues after time limits; progress is checked each time
# Extra sbatch options the shared-folder check job does not take: it must start now and needs next to nothing.
_NOT_FOR_CHECK = ("begin", "hold", "gres", "gpus-per-task", "cpus-per-gpu", "mem-per-cpu", "mem-per-gpu",
                  "time-min", "mail-type", "mail-user", "exclusive", "deadline", "nice", "priority")


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
        import_submitit()
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
    require_commands("sbatch", "squeue", "scancel")
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
            echo(f"again: {job.label} ({failure_reason(plan, job_id, states.get(job_id), job.log)})")
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
