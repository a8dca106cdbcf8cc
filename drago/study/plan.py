"""The plan of a study (``drago study``): every method x seed on the task sequence, the paper's transfer cases
of every run, and one report, worked out from what is on disk. Nothing here starts a process.

A study is a plan of jobs, each one ``drago`` command line:

* one sequence run per (method, seed) in ``OUT/METHOD/seedS``: ``drago train`` if it was never
  started, ``drago resume`` if it was interrupted, nothing if its ``summary.json`` says it is complete;
* for every run, the paper's transfer cases of its domain (paper §4.4) in
  ``RUN_DIR/transfer/TASK-afterK``, the same way (``drago transfer --task T --after K``, ``drago
  resume``, or nothing), each started once its run has finished. A case whose stage is beyond the
  sequence (a two-task run has no stage 3) is left out, and the plan says so;
* then the report over the runs (``OUT/report/report.html`` and ``report.md``) and the transfers'
  few-shot scores (``OUT/report/transfers.csv`` and ``transfers.md``).

With a records folder (``--records DIR``, meant to be committed), a study's unit of work is one run with its
transfer cases and the evaluations made from its checkpoints (:mod:`drago.eval.unit`), exported as one record,
``DIR/METHOD/seedS.json.gz``, as soon as the unit is finished. A unit whose record has the study's protocol is
skipped, on this machine or any other; one recorded with another protocol is run again (and its record
replaced); the report is built from the records. So the same command in a fresh clone continues where the
committed records stop (docs: Command line, "Records: studies that outlive the machine").

Because the plan is computed afresh from the directories, running the same command again after any
crash (a failed run, Ctrl-C, a SIGKILL of the study itself) finishes the study without redoing finished
work. A directory holding a run with other settings than the study's is an error, never mixed in.

The plan is carried out by a backend: child processes on this machine (:mod:`drago.study.local`) or SLURM
batch jobs (:mod:`drago.study.slurm`).
"""

from __future__ import annotations

import os
import statistics
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drago.config import Config, ConfigError, load_config, overrides_for, unread_overrides
from drago.continual import check_method, get_method
from drago.continual.base import Budget
from drago.envs import get_domain
from drago.report.transfers import TRANSFERS_CSV, TRANSFERS_MD
from drago.training.resources import keep_freed_memory_requested
from drago.training.records import (RECORD_SUFFIX, RecordError, protocol_diffs, read_record,
                                    settings_without_effect)
from drago.training.rundir import (SETTINGS_THAT_MAY_DIFFER, RunDirError, config_diffs, is_complete, is_run_dir,
                                   read_run_config, read_summary)
from drago.training.transfer import (
    DEFAULT_EPISODES,
    default_transfer_dir,
    few_shot_schedule,
    plan_transfer,
    resolve_task,
    reward_variant,
    transfer_config,
)

__all__ = ["DEFAULT_METHODS", "DEFAULT_PRESET", "DEFAULT_SEEDS", "Job", "StudyError", "StudyPlan", "available_cores",
           "default_study_dir", "describe_plan", "directory_state", "format_duration", "job_outcome", "job_wall_time",
           "parse_cases", "parse_seeds", "plan_study", "record_path", "record_verdict", "records_status",
           "summary_line", "transfer_argv"]

DEFAULT_PRESET = "minigrid-cpu"
DEFAULT_METHODS = ("drago", "continual", "ewc", "scratch", "replay", "drago-no-rehearsal", "drago-no-reviewer")
DEFAULT_SEEDS = (1, 2, 3)
LOG_FOLDER = "logs"
REPORT_FOLDER = "report"

START, RESUME, DONE = "start", "resume", "done"


class StudyError(RunDirError):
    """A study that cannot be planned or run as asked; the message is one line (the CLI prints it, exit 2)."""


def default_study_dir(preset: str) -> Path:
    return Path("runs") / "study" / preset


def parse_seeds(values: Iterable[str | int]) -> list[int]:
    """Seeds from ``1 2 3`` or ranges such as ``1-3``, in order, without duplicates.

    Raises:
        StudyError: a value that is neither a non-negative integer nor a range ``A-B`` with A <= B.
    """
    seeds: list[int] = []
    for value in values:
        text = str(value).strip()
        low, sep, high = text.partition("-")
        try:
            span = range(int(low), int(high) + 1) if sep and low else range(int(text), int(text) + 1)
        except ValueError:
            raise StudyError(f"--seeds takes non-negative integers or ranges like 1-3, got '{text}'") from None
        if not span or span.start < 0:
            raise StudyError(f"--seeds takes non-negative integers or ranges like 1-3, got '{text}'")
        seeds.extend(s for s in span if s not in seeds)
    return seeds


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


# ---------------------------------------------------------------------------------------------------
# planning
# ---------------------------------------------------------------------------------------------------
@dataclass(eq=False)
class Job:
    """One ``drago`` command of the study.

    Attributes:
        label: How the job is named in the study's output, e.g. ``drago seed1 room1to2-after2``.
        kind: ``run`` (a sequence run), ``transfer`` (one transfer case) or ``record`` (a finished unit's
            evaluations and record, with a records folder).
        method, seed: The run's (for a transfer, its source run's).
        directory: The run directory the job writes.
        state: What the plan found: ``start`` (never started), ``resume`` (interrupted) or ``done``.
        argv: The ``drago`` arguments that do the work (empty when done).
        log: Where the command's output goes.
        threads: ``train.threads`` the job runs with (0: all cores).
        source: For a transfer, the run job it waits for (None when that run was already complete).
        case: For a transfer, (test task, stage K).
        status: ``pending``, ``running``, ``done``, ``failed`` or ``blocked`` (its run failed).
        needs: Further jobs it waits for (a record job: its run and transfers).
        record: With a records folder, the unit's record file; ``recorded`` when that record, with the
            study's protocol, is what the job's work is taken from (the job is then done wherever it ran).
        protocol: The unit's protocol the record must have (a record job's, and a recorded unit's jobs').
    """

    label: str
    kind: str
    method: str
    seed: int
    directory: Path
    state: str
    argv: list[str]
    log: Path
    threads: int
    source: Job | None = None
    case: tuple[str, int] | None = None
    status: str = "pending"
    returncode: int | None = None
    seconds: float = 0.0
    needs: list[Job] = field(default_factory=list)
    record: Path | None = None
    recorded: bool = False
    protocol: dict[str, Any] | None = None


@dataclass
class StudyPlan:
    """Every job of a study in the order they are started: each run followed by its transfers."""

    preset: str
    out: Path
    methods: list[str]
    seeds: list[int]
    overrides: list[str]
    tasks: tuple[str, ...]
    jobs: int
    threads: int
    cores: int
    transfer_episodes: int
    transfer_eval_every: int
    cases: tuple[tuple[str, int], ...]
    budget: str = ""  # Budget.describe() of the runs' config
    transfer_reward: str | None = None  # dense or sparse: the transfers' reward, if not their runs' default
    transfer_few_shot_episodes: int | None = None  # None: 20, or the transfer's episodes if fewer
    own_cases: bool = False  # the cases were chosen (--cases), not the paper's
    records: Path | None = None  # the records folder, if units are recorded
    agent_kind: str = "tdmpc"  # the runs' agent kind, which decides the agent settings each run reads
    runs: list[Job] = field(default_factory=list)
    transfers: list[Job] = field(default_factory=list)
    record_jobs: list[Job] = field(default_factory=list)  # run locally; a SLURM study's report job records
    notes: list[str] = field(default_factory=list)

    def overrides_of(self, method: str) -> list[str]:
        """The study's overrides that a run of ``method`` reads (each method reads its own sections)."""
        return overrides_for(self.overrides, self.agent_kind, method)

    @property
    def report_dir(self) -> Path:
        return self.out / REPORT_FOLDER

    @property
    def ordered(self) -> list[Job]:
        order = []
        for run in self.runs:
            order.append(run)
            order.extend(t for t in self.transfers if t.method == run.method and t.seed == run.seed)
        return order


def directory_state(directory: Path) -> str:
    """START (missing or empty), DONE (its summary says complete) or RESUME (anything else) for a job's directory.

    What a study job does is decided from this alone, at plan time and again when a SLURM job starts or is
    requeued: ``drago train`` / ``drago transfer``, ``drago resume``, or nothing.
    """
    directory = Path(directory)
    if not directory.is_dir() or not any(directory.iterdir()):
        return START
    return DONE if is_complete(directory) else RESUME


def _state(directory: Path, wanted: Callable[[], Config], what: str, check: bool = True) -> tuple[str, Config | None]:
    """START, RESUME or DONE for ``directory``, and the config it holds; refuses other settings (if ``check``)."""
    if not directory.is_dir() or not any(directory.iterdir()):
        if directory.exists() and not directory.is_dir():
            raise StudyError(f"{directory} is a file, not a run directory; delete it or choose another --out")
        return START, None
    if not check:
        return directory_state(directory), None
    if not is_run_dir(directory):
        raise StudyError(f"{directory} is not empty and not a drago run; delete it or choose another --out")
    existing, wanted = read_run_config(directory), wanted()
    diffs = config_diffs(existing, wanted, ignore=(*SETTINGS_THAT_MAY_DIFFER, *settings_without_effect(wanted)))
    if diffs:
        more = f" and {len(diffs) - 3} more" if len(diffs) > 3 else ""
        raise StudyError(f"{directory} holds a {what} with other settings than this study's "
                         f"({'; '.join(diffs[:3])}{more}); choose another --out or delete {directory}")
    return (DONE if is_complete(directory) else RESUME), existing


def _budget_line(cfg: Config, methods: Sequence[str]) -> str:
    """The plan's budget line, with the schedules' clock where a method of the study has a second agent."""
    line = Budget.from_config(cfg).describe()
    if cfg.agent.schedule_clock == "learner" and any(get_method(m).second_agent for m in methods):
        line += "; schedules counted in the learner's steps (the official clock: agent.schedule_clock=task)"
    return line


def _has_threads(overrides: Sequence[str]) -> bool:
    return any(item.partition("=")[0].strip() in ("train.threads", "threads") for item in overrides)


def plan_study(preset: str = DEFAULT_PRESET, methods: Sequence[str] = DEFAULT_METHODS,
               seeds: Sequence[int] = DEFAULT_SEEDS, out: str | Path | None = None,
               overrides: Sequence[str] = (), jobs: int = 1, transfers: bool = True,
               transfer_episodes: int = DEFAULT_EPISODES, transfer_eval_every: int = 1,
               cores: int | None = None, check_settings: bool = True,
               transfer_reward: str | None = None, transfer_few_shot_episodes: int | None = None,
               cases: Sequence[tuple[str, int]] | None = None, records: str | Path | None = None) -> StudyPlan:
    """Work out what a study still has to do, from its directories.

    Args:
        preset: Preset of every run.
        methods: Continual methods (duplicates dropped).
        seeds: Seeds (duplicates dropped).
        out: The study folder (default ``runs/study/PRESET``).
        overrides: ``key=value`` settings for every run. Unless they set ``train.threads``, new runs get
            ``train.threads`` = max(1, cores // jobs).
        jobs: Runs at a time.
        transfers: Plan the paper's transfer cases of every run.
        transfer_episodes: Learner episodes of each transfer case.
        transfer_eval_every: Evaluate each transfer after every this many learner episodes.
        transfer_reward: ``dense`` or ``sparse`` for the transfers' reward (None: each run's default, its
            ``transfer.reward`` or the test task's own); a reward other than that default gets directories of
            its own (``TASK-REWARD-afterK``), so a study can hold both.
        transfer_few_shot_episodes: Read each transfer's few-shot score after this many learner episodes
            (None: 20, or ``transfer_episodes`` if fewer).
        cases: ``(task, stage K)`` transfer cases instead of the paper's: any task of the domain (a training
            task is relearned) or a test task of the catalogue.
        cores: CPU cores to share (default: those this process may use).
        check_settings: Refuse directories holding runs with other settings (off for ``--status``, which
            only reads what is there).
        records: The records folder: units recorded there with this study's protocol are skipped, the
            others are recorded there once finished (see the module docstring).

    Raises:
        StudyError: A bad argument, or a directory holding something other than what the study would
            create there (one line naming it).
        ConfigError: An unknown preset, method or setting, or a bad ``DRAGO_KEEP_FREED_MEMORY``.
    """
    keep_freed_memory_requested()  # checked once here: every job would fail on it
    methods = list(dict.fromkeys(methods))
    seeds = list(dict.fromkeys(int(s) for s in seeds))
    if not methods:
        raise StudyError("name at least one method")
    if not seeds or any(s < 0 for s in seeds):
        raise StudyError(f"seeds must be non-negative integers, got {' '.join(map(str, seeds)) or 'none'}")
    if jobs < 1:
        raise StudyError(f"--jobs must be a positive integer, got {jobs}")
    if transfer_reward not in (None, "dense", "sparse"):
        raise StudyError(f"--transfer-reward must be dense or sparse, got {transfer_reward}")
    try:  # the check `drago transfer` makes, at plan time rather than when the first transfer starts
        few_shot_schedule(transfer_episodes, transfer_few_shot_episodes, transfer_eval_every, flag="--transfer-")
    except ConfigError as err:
        raise StudyError(str(err)) from None
    cores = cores or available_cores()
    overrides = list(overrides)
    if not _has_threads(overrides):
        overrides.append(f"train.threads={max(1, cores // jobs)}")
    out = Path(out) if out is not None else default_study_dir(preset)
    base = check_method(load_config(preset, overrides, method=methods[0], seed=seeds[0], inapplicable_ok=True))
    unread = unread_overrides(overrides, base.agent.kind, methods)
    if unread:
        raise StudyError(unread)
    if transfer_reward is not None and not get_domain(base.env.domain).dense_reward:
        raise StudyError(f"--transfer-reward applies to the grid only (a dense and a sparse reward); leave it out "
                         f"for {base.env.domain}")
    n_tasks = len(base.env.tasks)
    paper = cases is None
    if cases is not None:
        cases = tuple(dict.fromkeys((str(task), int(after)) for task, after in cases))
        _check_cases(base, cases, n_tasks)
    else:
        cases = get_domain(base.env.domain).transfer_cases
    cases = cases if transfers else ()
    kept = tuple((task, after) for task, after in cases if after <= n_tasks)
    plan = StudyPlan(preset=preset, out=out, methods=methods, seeds=seeds, overrides=overrides,
                     tasks=tuple(base.env.tasks), jobs=jobs, threads=base.train.threads, cores=cores,
                     transfer_episodes=transfer_episodes, transfer_eval_every=transfer_eval_every, cases=kept,
                     budget=_budget_line(base, methods), transfer_reward=transfer_reward,
                     transfer_few_shot_episodes=transfer_few_shot_episodes, own_cases=bool(cases) and not paper,
                     records=None if records is None else Path(records), agent_kind=base.agent.kind)
    if transfers and not cases:
        plan.notes.append(f"domain {base.env.domain} declares no transfer cases: none planned")
    left_out = [f"{task} after {after}" for task, after in cases if after > n_tasks]
    if left_out:
        plan.notes.append(f"transfer cases left out, the sequence has {n_tasks} task{'s' * (n_tasks != 1)}: "
                          + ", ".join(left_out))
    if jobs > cores:
        plan.notes.append(f"--jobs {jobs} is more than the {cores} cores: the runs will share them")

    logs = out / LOG_FOLDER
    for seed in seeds:
        for method in methods:
            own = plan.overrides_of(method)
            cfg = check_method(load_config(preset, own, method=method, seed=seed))
            run_dir = out / method / f"seed{seed}"
            label = f"{method} seed{seed}"
            if plan.records is not None and _plan_recorded_unit(plan, cfg, run_dir, label, logs, kept):
                continue
            state, existing = _state(run_dir, lambda cfg=cfg: cfg, "run", check_settings)
            argv = {START: ["train", preset, "--method", method, "--seed", str(seed), "--out", str(run_dir),
                            "--no-progress", *own],
                    RESUME: ["resume", str(run_dir), "--no-progress"], DONE: []}[state]
            source_cfg = existing or cfg
            run = Job(label, "run", method, seed, run_dir, state, argv, logs / f"{method}-seed{seed}.log",
                      source_cfg.train.threads)
            plan.runs.append(run)
            transfers = [_transfer_job(run, source_cfg, task, after, plan, logs, check_settings)
                         for task, after in kept]
            plan.transfers.extend(transfers)
            if plan.records is not None:
                _plan_record_job(plan, cfg, run, transfers, logs)
    resumed = sorted({j.threads for j in plan.runs if j.state == RESUME and j.threads != plan.threads})
    if resumed:
        plan.notes.append(f"interrupted runs keep the train.threads they started with "
                          f"({', '.join(map(str, resumed))}; 0 is every core)")
    return plan


def record_path(records: Path, method: str, seed: int) -> Path:
    """Where a study keeps the record of one unit."""
    return Path(records) / method / f"seed{seed}{RECORD_SUFFIX}"


def _wanted_protocol(plan: StudyPlan, cfg: Config, run_dir: Path,
                     kept: Sequence[tuple[str, int]]) -> dict[str, Any]:
    """The protocol a unit of this study records: its run's config and those its transfer cases will write
    (their checkpoint paths aside, which no protocol holds)."""
    from drago.eval.unit import unit_protocol

    dense = None if plan.transfer_reward is None else plan.transfer_reward == "dense"
    transfers = {}
    for task, after in kept:
        _, case = resolve_task(cfg, task)
        pre = {"pre_rollout_checkpoint": "-"} if case is not None and case.pre_rollout_source is not None else {}
        name = default_transfer_dir(run_dir, task, after, reward_variant(cfg, task, dense)).name
        transfers[name] = transfer_config(cfg, task, "-", after, episodes=plan.transfer_episodes,
                                          few_shot_episodes=plan.transfer_few_shot_episodes,
                                          eval_every=plan.transfer_eval_every, dense_reward=dense, **pre)
    return unit_protocol(cfg, transfers)


def record_verdict(path: Path, protocol: dict[str, Any]) -> str | None:
    """None when ``path`` is a readable record with ``protocol``; else why it is not used (one phrase)."""
    from drago.training.records import protocol_digest

    if not path.is_file():
        return "missing"
    try:
        found = read_record(path)
    except RecordError as err:
        return str(err)
    if found["protocol"]["digest"] == protocol_digest(protocol):
        return None
    return f"{path} was recorded with another protocol ({protocol_diffs(found['protocol'], protocol)})"


def _plan_recorded_unit(plan: StudyPlan, cfg: Config, run_dir: Path, label: str, logs: Path,
                        kept: Sequence[tuple[str, int]]) -> bool:
    """Add a unit whose record has the study's protocol as done jobs; False (nothing added) otherwise."""
    protocol = _wanted_protocol(plan, cfg, run_dir, kept)
    path = record_path(plan.records, cfg.method.name, cfg.train.seed)
    verdict = record_verdict(path, protocol)
    if verdict is not None:
        if verdict != "missing":
            plan.notes.append(f"not used: its unit is made again here and a new record replaces it (the run and "
                              f"transfers the study folder already holds finished are kept): {verdict}")
        return False
    method, seed = cfg.method.name, cfg.train.seed
    run = Job(label, "run", method, seed, run_dir, DONE, [], logs / f"{method}-seed{seed}.log", cfg.train.threads,
              record=path, recorded=True, protocol=protocol)
    plan.runs.append(run)
    dense = None if plan.transfer_reward is None else plan.transfer_reward == "dense"
    for task, after in kept:
        case_dir = default_transfer_dir(run_dir, task, after, reward_variant(cfg, task, dense))
        plan.transfers.append(Job(f"{label} {case_dir.name}", "transfer", method, seed, case_dir, DONE, [],
                                  logs / f"{method}-seed{seed}-{case_dir.name}.log", cfg.train.threads,
                                  case=(task, after), record=path, recorded=True, protocol=protocol))
    return True


def _plan_record_job(plan: StudyPlan, cfg: Config, run: Job, transfers: Sequence[Job], logs: Path) -> None:
    """The job that evaluates and records a unit once its run and transfers have finished."""
    protocol = _wanted_protocol(plan, cfg, run.directory, [t.case for t in transfers if t.case is not None])
    path = record_path(plan.records, run.method, run.seed)
    for job in (run, *transfers):
        job.record, job.protocol = path, protocol
    plan.record_jobs.append(Job(f"{run.label} record", "record", run.method, run.seed, run.directory, START,
                                ["record", str(run.directory), "--out", str(path)],
                                logs / f"{run.method}-seed{run.seed}-record.log", 1,
                                needs=[j for j in (run, *transfers) if j.state != DONE], record=path,
                                protocol=protocol))


def _check_cases(cfg: Config, cases: Sequence[tuple[str, int]], n_tasks: int) -> None:
    for task, after in cases:
        try:
            resolve_task(cfg, task)
        except ConfigError as err:
            raise StudyError(f"--cases {task}:{after}: {err}") from None
        if not 1 <= after <= n_tasks:
            raise StudyError(f"--cases {task}:{after}: the stage must be between 1 and {n_tasks}, the tasks of the "
                             f"sequence ({', '.join(cfg.env.tasks)})")


def parse_cases(items: Sequence[str]) -> list[tuple[str, int]]:
    """``TASK:K`` arguments as ``(task, K)`` pairs.

    Raises:
        StudyError: an item without a positive integer after its colon (one line naming it).
    """
    cases = []
    for item in items:
        task, colon, after = item.rpartition(":")
        if not (task and colon and after.isdigit() and int(after) > 0):
            raise StudyError(f"--cases takes TASK:K with K the stage the world model is taken after, e.g. "
                             f"room1to2:2; got '{item}'")
        cases.append((task, int(after)))
    return cases


def transfer_argv(run_dir: Path, task: str, after: int, plan: StudyPlan) -> list[str]:
    """The ``drago transfer`` command of one case of the study."""
    reward = ["--reward", plan.transfer_reward] if plan.transfer_reward else []
    few_shot = ([] if plan.transfer_few_shot_episodes is None else
                ["--few-shot-episodes", str(plan.transfer_few_shot_episodes)])
    return ["transfer", str(run_dir), "--task", task, "--after", str(after), "--episodes", str(plan.transfer_episodes),
            *few_shot, "--eval-every", str(plan.transfer_eval_every), *reward, "--no-progress"]


def _transfer_job(run: Job, source: Config, task: str, after: int, plan: StudyPlan, logs: Path,
                  check: bool = True) -> Job:
    dense = None if plan.transfer_reward is None else plan.transfer_reward == "dense"
    variant = reward_variant(source, task, dense)
    case_dir = default_transfer_dir(run.directory, task, after, variant)
    name = case_dir.name  # TASK-afterK, or TASK-REWARD-afterK

    def wanted() -> Config:
        # Exactly the config `drago transfer RUN_DIR --task T --after K --episodes N ...` would write.
        return plan_transfer(run.directory, task, after, None, episodes=plan.transfer_episodes,
                             few_shot_episodes=plan.transfer_few_shot_episodes, eval_every=plan.transfer_eval_every,
                             dense_reward=dense)[0]

    state, _ = _state(case_dir, wanted, "transfer", check)
    argv = {START: transfer_argv(run.directory, task, after, plan),
            RESUME: ["resume", str(case_dir), "--no-progress"], DONE: []}[state]
    return Job(f"{run.label} {name}", "transfer", run.method, run.seed, case_dir, state, argv,
               logs / f"{run.method}-seed{run.seed}-{name}.log", run.threads,
               source=run if run.state != DONE else None, case=(task, after))


def _counts(jobs: Sequence[Job]) -> str:
    n = {state: sum(j.state == state for j in jobs) for state in (START, RESUME, DONE)}
    return f"{n[START]} to start, {n[RESUME]} to resume, {n[DONE]} finished (skipped)"


def format_duration(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m {seconds % 60:02d}s"
    return f"{seconds // 3600}h {seconds % 3600 // 60:02d}m"


def job_wall_time(job: Job) -> float | None:
    """Seconds a finished job took, from its summary."""
    try:
        summary = read_summary(job.directory)  # None before the first task: a TypeError below
        if job.kind == "transfer":
            return float(summary["transfer"]["wall_time_s"])
        return float(sum(t["wall_time_s"] for t in summary["tasks"]))
    except (RunDirError, KeyError, TypeError):
        return None


def _estimate(plan: StudyPlan) -> str | None:
    """Time left from the wall times of the study's finished jobs (None before any has finished)."""
    total, counted, basis = 0.0, True, []
    for kind, jobs in (("run", plan.runs), ("transfer", plan.transfers)):
        left = sum(j.state != DONE for j in jobs)
        times = [t for t in (job_wall_time(j) for j in jobs if j.state == DONE) if t is not None]
        if times:
            total += left * statistics.mean(times)
            basis.append(f"{len(times)} finished {kind}{'s' * (len(times) != 1)}")
        elif left:
            counted = False
    if not basis or not total:
        return None
    rest = "" if counted else "; jobs of a kind none of which has finished yet are not counted"
    return (f"about {format_duration(total / plan.jobs)} left at --jobs {plan.jobs} (mean wall time of "
            f"{' and '.join(basis)}{rest})")


def describe_plan(plan: StudyPlan, verbose: bool = False, resources: Sequence[str] | None = None) -> list[str]:
    """The plan as console lines; ``verbose`` adds one line per run.

    ``resources`` replaces the line on local jobs and cores (and the time estimate, which assumes them):
    a SLURM study describes its batch jobs instead.
    """
    n_runs = len(plan.runs)
    lines = [f"drago study {plan.preset} into {plan.out}: {len(plan.methods)} method{'s' * (len(plan.methods) != 1)}"
             f" x {len(plan.seeds)} seed{'s' * (len(plan.seeds) != 1)} = {n_runs} run{'s' * (n_runs != 1)} of "
             f"{' -> '.join(plan.tasks)}",
             f"  methods:   {', '.join(plan.methods)}; seeds: {', '.join(map(str, plan.seeds))}",
             f"  runs:      {_counts(plan.runs)}"]
    if plan.budget:
        lines.append(f"  budget:    {plan.budget}")
    if plan.cases:
        cases = ", ".join(f"{task} after {after}" for task, after in plan.cases)
        lines += [f"  transfers: {_counts(plan.transfers)}; cases {cases}, "
                  f"{plan.transfer_episodes} learner episode{'s' * (plan.transfer_episodes != 1)} each"
                  f"{f' with {plan.transfer_reward} reward' if plan.transfer_reward else ''}, "
                  f"evaluated after every {'' if plan.transfer_eval_every == 1 else f'{plan.transfer_eval_every} '}"
                  f"episode{'s' * (plan.transfer_eval_every != 1)}"
                  + ("" if plan.transfer_few_shot_episodes is None
                     else f", few-shot score after {plan.transfer_few_shot_episodes}")]
    if resources is None:
        lines.append(f"  jobs:      {plan.jobs} at a time on {plan.cores} core{'s' * (plan.cores != 1)}, new runs with "
                     f"train.threads={plan.threads}; each job's output in {plan.out / LOG_FOLDER}/")
        estimate = _estimate(plan)
        if estimate:
            lines.append(f"  time:      {estimate}")
    else:
        lines += resources
    if plan.records is not None:
        recorded = sum(run.recorded for run in plan.runs)
        lines.append(f"  records:   {plan.records}/METHOD/seedS{RECORD_SUFFIX}: {recorded} unit{'s' * (recorded != 1)} "
                     f"recorded (skipped), {len(plan.record_jobs)} to record once finished")
    report = f"{plan.report_dir / 'report.html'} and report.md"
    if plan.cases:
        report += f", with {TRANSFERS_CSV} and {TRANSFERS_MD} for the transfers"
    lines.append(f"  report:    {report}")
    lines += [f"  note:      {note}" for note in plan.notes]
    if verbose:
        width = max(len(j.label) for j in plan.runs)
        for run in plan.runs:
            mine = [t for t in plan.transfers if (t.method, t.seed) == (run.method, run.seed)]
            extra = "  transfers: " + " ".join(t.state for t in mine) if mine else ""
            lines.append(f"    {run.label:<{width}}  {run.state:<6}{extra}")
    return lines


# ---------------------------------------------------------------------------------------------------
# reading what the jobs did
# ---------------------------------------------------------------------------------------------------
def summary_line(plan: StudyPlan, finished: Sequence[Job], failures: Sequence[tuple[Job, str]],
                 blocked: Sequence[Job], report_error: str | None, ran: str = "run") -> str:
    """The last line of a study command, for any backend: complete, or what failed and how to go on.

    Args:
        failures: each failed job with why, e.g. its exit code and log.
        ran: how the jobs ran ("run", "run through SLURM").
    """
    if not failures and not blocked and report_error is None:
        skipped = sum(j.state == DONE for j in plan.ordered)
        return (f"study complete: {len(finished)} job{'s' * (len(finished) != 1)} {ran}, {skipped} "
                f"already finished; report in {plan.report_dir / 'report.html'}")
    parts = []
    if failures:
        job, why = failures[0]
        parts.append(f"{len(failures)} job{'s' * (len(failures) != 1)} failed (first: {job.label}, {why})")
    if blocked:
        parts.append(f"{len(blocked)} transfer{'s' * (len(blocked) != 1)} not started")
    if report_error:
        parts.append(f"no report ({report_error})")
    return f"study incomplete: {'; '.join(parts)}; run the same command again to continue"


def job_outcome(job: Job) -> str:
    """A short result of a finished job for its console line."""
    if job.kind == "record":
        return f"{job.record} ({job.record.stat().st_size / 1024:.0f} KiB)" if job.record.is_file() else ""
    try:
        summary = read_summary(job.directory)  # None before the first task: a TypeError below
        if job.kind == "transfer":
            point = summary["transfer"]["few_shot"]["equal_episodes"]
            frac = point.get("fraction_of_optimal")
            return f"few-shot return {point['return']:.1f}" + (f" ({frac:.0%} of optimal)" if frac is not None else "")
        ends = [f"{t['name']} {t['fraction_of_optimal']:.0%}" for t in summary["tasks"]
                if t.get("fraction_of_optimal") is not None]
        return ("final eval, of optimal: " + ", ".join(ends)) if ends else ""
    except (RunDirError, KeyError, TypeError):
        return ""


def _cpu_seconds(job: Job) -> float:
    """CPU seconds of a job's finished tasks (0 before its first)."""
    summary = read_summary(job.directory) if is_run_dir(job.directory) else None
    return sum(float(t.get("cpu_time_s", 0.0)) for t in (summary or {}).get("tasks", []))


def records_status(plan: StudyPlan) -> list[str]:
    """``--status`` of a study with a records folder: units recorded, in progress and to do, and the CPU-hours
    left, estimated from the recorded units' own CPU time (per method where one is recorded); before any unit is
    recorded, from the study's finished runs and transfers, with the record jobs' evaluations not counted."""
    from drago.eval.unit import unit_cpu_seconds

    if plan.records is None:
        return []
    spent: dict[str, list[float]] = {}
    for run in plan.runs:
        if run.recorded:
            spent.setdefault(run.method, []).append(unit_cpu_seconds(read_record(run.record)))
    every = [s for values in spent.values() for s in values]
    # Before the first record (a study whose units take hours each), what the study's own finished jobs cost.
    finished: dict[str, dict[str, list[float]]] = {"run": {}, "transfer": {}}
    if not every:
        for job in (*plan.runs, *plan.transfers):
            if job.state == DONE:
                finished[job.kind].setdefault(job.method, []).append(_cpu_seconds(job))

    def job_mean(kind: str, method: str) -> float | None:
        basis = finished[kind].get(method) or [s for values in finished[kind].values() for s in values]
        return statistics.mean(basis) if basis else None

    left, unknown, started, todo = 0.0, [], 0, 0
    for run in plan.runs:
        if run.recorded:
            continue
        if is_run_dir(run.directory):
            started += 1
        else:
            todo += 1
        done = _cpu_seconds(run) if is_run_dir(run.directory) else 0.0
        basis = spent.get(run.method) or every
        if basis:
            left += max(0.0, statistics.mean(basis) - done)
            continue
        parts = [] if run.state == DONE else [(job_mean("run", run.method), done)]
        parts += [(job_mean("transfer", t.method), _cpu_seconds(t)) for t in plan.transfers
                  if (t.method, t.seed) == (run.method, run.seed) and t.state != DONE]
        if any(mean is None for mean, _ in parts):
            unknown.append(run.label)
            continue
        left += sum(max(0.0, mean - done) for mean, done in parts)
    recorded = sum(run.recorded for run in plan.runs)
    lines = [f"  units:   {recorded} recorded in {plan.records}, {started} in progress here, {todo} to do"]
    if recorded < len(plan.runs):
        counted = len(unknown) < len(plan.runs) - recorded
        estimate = (f"about {left / 3600:.1f} CPU-hours ({format_duration(left)}) left (mean CPU time of the "
                    f"recorded units of the same method, else of all {len(every)}; the finished tasks of units in "
                    "progress counted off)" if every else
                    f"about {left / 3600:.1f} CPU-hours ({format_duration(left)}) left before the units' evaluations "
                    f"(no unit recorded yet: mean CPU time of the study's finished runs and transfers of the same "
                    f"method, else of all; the finished tasks of jobs in progress counted off)" if counted else
                    "CPU-hours left: unknown until a unit is recorded or a run finishes")
        if counted and unknown:
            estimate += f"; not counted: {', '.join(unknown)}"
        lines.append(f"  cost:    {estimate}")
    return lines
