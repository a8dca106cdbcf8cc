"""The ``drago`` command: parses, validates, calls the library. No logic of its own.

Every user error ends as one line ``drago: error: ...`` on stderr with exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from pathlib import Path

EXIT_USAGE = 2


class UsageError(Exception):
    """Raised instead of printing argparse's multi-line usage block."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # noqa: D102 (argparse hook)
        raise UsageError(message)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="drago", description="Continual model-based RL: DRAGO and its baselines.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    train = sub.add_parser("train", help="run a continual task sequence",
                           usage="drago train PRESET [options] [key=value ...]",
                           epilog="key=value overrides any setting, e.g. agent.tdmpc.mlp_dim=256 "
                                  "(see `drago list --settings`)")
    train.add_argument("preset", help="preset name (see `drago list`)")
    train.add_argument("--method", default=None, help="continual method (default: the preset's, continual)")
    train.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's, 1)")
    train.add_argument("--out", type=Path, default=None, help="run directory (default runs/PRESET/METHOD/seedS)")
    train.add_argument("--force", action="store_true", help="overwrite an existing run directory")
    train.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")
    train.add_argument("--smoke", action="store_true",
                       help="the preset's smoke path: its tasks and agent at the smoke preset's budgets and sizes, "
                            "a run of seconds (default folder runs/PRESET+smoke/...)")

    resume = sub.add_parser("resume", help="continue a run that was interrupted")
    resume.add_argument("run_dir", type=Path)
    resume.add_argument("--no-progress", action="store_true")

    listing = sub.add_parser("list", help="presets, tasks and methods (and settings with --settings)")
    listing.add_argument("--settings", action="store_true", help="also list every setting with its default")

    evaluate = sub.add_parser("eval", help="evaluate finished runs (see `drago eval coverage -h`)")
    eval_sub = evaluate.add_subparsers(dest="eval_command", metavar="EVALUATION", parser_class=_Parser)
    eval_sub.required = True
    coverage = eval_sub.add_parser("coverage", help="world-model accuracy per room after each task (grid)",
                                   usage="drago eval coverage RUN_DIR [RUN_DIR ...] [--out CSV]",
                                   description="Writes coverage.csv into each run directory.")
    coverage.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR")
    coverage.add_argument("--out", type=Path, default=None, metavar="CSV",
                          help="also write every run's rows into this one CSV")
    heldout = eval_sub.add_parser(
        "heldout", help="retention matrix: each stage's world model on every task's held-out transitions (DMC)",
        usage="drago eval heldout RUN_DIR [RUN_DIR ...] [--out CSV]",
        description="Scores the world model after each stage on the held-out set of every task (prediction "
                    "error and -log error), recording missing sets from the task checkpoints. Writes "
                    "retention.csv into each run directory.")
    heldout.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR")
    heldout.add_argument("--out", type=Path, default=None, metavar="CSV",
                         help="also write every run's rows into this one CSV")
    zero_shot = eval_sub.add_parser(
        "zero-shot", help="zero-shot return matrix: plan with each stage's world model and the true reward (grid)",
        usage="drago eval zero-shot RUN_DIR [RUN_DIR ...] [--tasks T ...] [--reward R ...] [--episodes N] "
              "[--horizon H] [--epsilon E] [--out CSV]",
        description="Plays every task with the world model after each stage and the task's true reward, no "
                    "learned head and no learning (docs: Evaluation, zero-shot planning): R[stage, task] as "
                    "return and fraction of the DP optimum, with ACC/BWT over the training rooms. Writes "
                    "zero_shot.csv into each run directory.")
    zero_shot.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR")
    zero_shot.add_argument("--tasks", nargs="+", default=None, metavar="T",
                           help="tasks to play (default: the run's training rooms, then the paper's transfer tasks)")
    zero_shot.add_argument("--reward", nargs="+", choices=("task", "dense", "sparse"), default=["task"],
                           help="reward readings (default task: training rooms dense, transfer tasks sparse)")
    zero_shot.add_argument("--episodes", type=int, default=4, metavar="N",
                           help="episodes per cell; episode e starts facing heading e mod 4 (default 4)")
    zero_shot.add_argument("--horizon", type=int, default=None, metavar="H",
                           help="planner lookahead in steps (default: the whole episode)")
    zero_shot.add_argument("--epsilon", type=float, default=None, metavar="E",
                           help="share of steps played with a random action, so that one wrong transition on "
                                "the route does not trap the planner for the rest of the episode (default 0.05; "
                                "0: deterministic)")
    zero_shot.add_argument("--out", type=Path, default=None, metavar="CSV",
                           help="also write every run's rows into this one CSV")
    components = eval_sub.add_parser(
        "components", help="which part forgot: each part of the agent on every earlier task, the swap test, and "
                           "what the run carries and spends (grid)",
        usage="drago eval components RUN_DIR [RUN_DIR ...]",
        description="Measures the world model's one- and H-step dynamics, each task's reward, value and policy "
                    "heads and planning with them on every earlier task's probe after each stage, the swap test "
                    "(saved, moved and refit heads, true reward) and the bytes carried across each task boundary "
                    "(docs: Evaluation, which part forgot). Writes components.csv, swap.csv and costs.csv into "
                    "each run directory.")
    components.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR")
    _add_transfer_parser(sub)
    _add_report_parser(sub)
    _add_record_parser(sub)
    _add_study_parser(sub)
    return parser


def _cmd_train(args: argparse.Namespace) -> int:
    from drago.api import continue_with, default_run_dir, load_config, new_run, speed_summary

    if args.seed is not None and args.seed < 0:
        raise UsageError(f"--seed must be a non-negative integer, got {args.seed}")
    cfg = load_config(args.preset, args.overrides, method=args.method, seed=args.seed, smoke=args.smoke)
    run_dir = args.out or default_run_dir(cfg)
    trainer = new_run(cfg, run_dir, force=args.force, progress=not args.no_progress)
    trainer.logger.print(f"drago train {cfg.preset} --method {cfg.method.name} --seed {cfg.train.seed} -> {run_dir} "
                         f"({speed_summary(trainer.cfg.agent)})")
    for note in trainer.speed_notes:
        trainer.logger.print(note)
    # Closing flushes TensorBoard and ends the W&B run (marked failed when an exception is on its way out).
    try:
        with continue_with(f"continue with `drago resume {run_dir}`"):
            trainer.run()
    finally:
        trainer.logger.close()
    return 0


def _cmd_resume(args: argparse.Namespace) -> int:
    from drago.api import continue_with, resume

    trainer = resume(args.run_dir, progress=not args.no_progress)
    done = trainer.completed_tasks()
    if done == len(trainer.cfg.env.tasks):
        trainer.logger.print(f"{args.run_dir} is already complete ({done} tasks); nothing to do")
        trainer.write_summary()
        return 0
    trainer.logger.print(f"resuming {args.run_dir}: {done} of {len(trainer.cfg.env.tasks)} tasks complete")
    try:
        with continue_with(f"continue with `drago resume {args.run_dir}`"):
            trainer.run()
    finally:
        trainer.logger.close()
    return 0


def _cmd_list(args: argparse.Namespace) -> int:
    from drago.api import (agent_kinds, available_domains, available_presets, describe_settings_fully,
                           get_domain, methods, plugin_packages, plugin_problems, task_descriptions)

    packages = plugin_packages()
    print("presets:  " + ", ".join(f"{name} (package {packages['presets'][name]})" if name in packages["presets"]
                                   else name for name in available_presets()) + " (or a path to a YAML file)")
    print("methods:")
    for name, cls in methods().items():
        origin = f" (package {packages['methods'][name]})" if name in packages["methods"] else ""
        print(f"  {name:<20} {cls.description}{origin}")
    print("agents:")
    for name, kind in agent_kinds().items():
        print(f"  {name:<20} {kind.description} (agent.kind={name})")
    domains = {name: get_domain(name) for name in available_domains()}
    tasks = {name: task_descriptions(name) for name in domains}
    width = max(len(name) for rows in tasks.values() for name, _ in rows)
    for name, rows in tasks.items():
        origin = f", package {packages['domains'][name]}" if name in packages["domains"] else ""
        print(f"tasks ({name}, env.domain={name}{origin}):")
        for task, description in rows:
            print(f"  {task:<{width}}  {description}")
    print("  (every stock DeepMind Control task too: env.domain=dmc:DOMAIN, e.g. dmc:hopper with hopper-stand)")
    print("sequences:")
    for domain in domains.values():
        for name, sequence in domain.sequences.items():
            print(f"  {name:<{width}}  {' -> '.join(sequence)}")
    problems = plugin_problems()
    if problems:
        print("plug-ins skipped:")
        for problem in problems:
            print(f"  {problem}")
    if args.settings:
        print("settings (key, type, default: what it does):")
        for key, kind, default, description in describe_settings_fully():
            print(f"  {key:<34} {kind:<18} {str(default) + ':':<12} {description}")
    return 0


def _cmd_eval_coverage(args: argparse.Namespace) -> int:
    from drago.api import COVERAGE_FILE, coverage, coverage_checkpoints, format_coverage_table, write_coverage_csv

    _evaluate_runs(args, check=coverage_checkpoints, measure=coverage, write=write_coverage_csv,
                   filename=COVERAGE_FILE, title="exact-match accuracy of the world model after each task:",
                   table=format_coverage_table)
    return 0


def _cmd_eval_heldout(args: argparse.Namespace) -> int:
    from drago.api import (RETENTION_FILE, format_retention_table, retention_checkpoints, retention_matrix,
                           write_retention_csv)

    _evaluate_runs(args, check=retention_checkpoints,
                   measure=lambda run_dir: retention_matrix(run_dir, record_missing=True),
                   write=write_retention_csv, filename=RETENTION_FILE,
                   title="prediction score -log(MSE) of the world model after each stage (rows) "
                         "on each task's held-out set:", table=format_retention_table)
    return 0


def _cmd_eval_zero_shot(args: argparse.Namespace) -> int:
    from drago.api import (ZERO_SHOT_FILE, format_zero_shot_table, zero_shot_checkpoints, zero_shot_matrix,
                           zero_shot_metrics, write_zero_shot_csv)

    chosen = {name: value for name, value in (("horizon", args.horizon), ("epsilon", args.epsilon))
              if value is not None}
    rows = _evaluate_runs(args, check=zero_shot_checkpoints,
                          measure=lambda run_dir: zero_shot_matrix(run_dir, tasks=args.tasks, episodes=args.episodes,
                                                                   readings=args.reward, **chosen),
                          write=write_zero_shot_csv, filename=ZERO_SHOT_FILE,
                          title="zero-shot return as a fraction of the DP optimum, planning with the world model "
                                "after each stage and the true reward (* a paper transfer case):",
                          table=format_zero_shot_table)
    metrics = zero_shot_metrics(rows)
    if metrics:
        print("continual-learning metrics of R[stage, training room] (fraction of the DP optimum):")
        for m in metrics:
            print(f"  {m['run']}  {m['reward']}  stages {m['stages']}  ACC {m['acc']:.3f}  BWT {m['bwt']:+.3f}")
    return 0


def _cmd_eval_components(args: argparse.Namespace) -> int:
    from drago.api import components_checkpoints, evaluate_components

    for run_dir in args.run_dirs:
        components_checkpoints(run_dir)
    for run_dir in args.run_dirs:
        swaps, written = evaluate_components(run_dir)
        print(f"{run_dir}: return on an earlier task as a fraction of its DP optimum (swap test)")
        print(f"  {'task':<8} {'after':>5} {'saved':>6} {'moved':>6} {'refit':>6} {'refit range':>11} "
              f"{'true reward':>11}")
        for row in swaps:
            share = {key: (f"{float(row[key]) / row['optimum']:.2f}" if row[key] != "" else "–")
                     for key in ("saved", "moved", "refit", "refit_min", "refit_max", "true_reward")}
            spread = f"{share['refit_min']}-{share['refit_max']}"
            print(f"  {row['task']:<8} {row['stage']:>5} {share['saved']:>6} {share['moved']:>6} {share['refit']:>6} "
                  f"{spread:>11} {share['true_reward']:>11}")
        for path in written:
            print(f"wrote {path}")
    return 0


def _evaluate_runs(args: argparse.Namespace, check, measure, write, filename: str, title: str, table) -> list[dict]:
    """Measure every run's world models into a CSV per run (and optionally one for all), with a text table;
    returns every run's rows. A record (``*.json.gz``) gives the evaluation it recorded, read, not measured:
    its checkpoints stayed on the machine that trained it."""
    from drago.api import RECORD_SUFFIX, recorded_evaluation

    records = [path for path in args.run_dirs if path.name.endswith(RECORD_SUFFIX)]
    run_dirs = [path for path in args.run_dirs if path not in records]
    # Check every run before evaluating any, so a typo in the last argument fails at once.
    for run_dir in run_dirs:
        check(run_dir)
    rows = []
    for record in records:
        found = recorded_evaluation(record, filename)
        if not found:
            raise UsageError(f"{record} holds no {filename}; it was not recorded for this run's domain")
        rows.extend(found)
    for run_dir in run_dirs:
        run_rows = measure(run_dir)
        write(run_rows, run_dir / filename)
        rows.extend(run_rows)
    print(title)
    for line in table(rows):
        print(line)
    for record in records:
        print(f"read {filename} from the record {record}")
    for run_dir in run_dirs:
        print(f"wrote {run_dir / filename}")
    if args.out is not None:
        print(f"wrote {write(rows, args.out)}")
    return rows


def _cmd_eval(args: argparse.Namespace) -> int:
    return {"coverage": _cmd_eval_coverage, "heldout": _cmd_eval_heldout,
            "zero-shot": _cmd_eval_zero_shot, "components": _cmd_eval_components}[args.eval_command](args)


COMMANDS = {"train": _cmd_train, "resume": _cmd_resume, "list": _cmd_list, "eval": _cmd_eval}


# ---- drago transfer ---------------------------------------------------------------------------------
def _add_transfer_parser(sub) -> None:
    transfer = sub.add_parser(
        "transfer", help="learn a test task from the world model a run saved after stage K",
        usage="drago transfer RUN_DIR (--task T --after K | --paper-cases) [--episodes N] [--learner-only] "
              "[--out DIR] [--force] [--no-progress]",
        description="Trains TASK for N learner episodes starting from the world model (and DRAGO's VAE and "
                    "threshold) saved after stage K of RUN_DIR, with fresh heads, evaluating after every episode. "
                    "Writes RUN_DIR/transfer/TASK-afterK; continue an interrupted one with `drago resume DIR`.")
    transfer.add_argument("run_dir", type=Path, metavar="RUN_DIR")
    transfer.add_argument("--task", default=None, help="task to learn (a test task, or a training task to relearn); "
                                                       "DMC test tasks by their Table 1 name, e.g. jump2run")
    transfer.add_argument("--after", type=int, default=None, metavar="K",
                          help="use the world model saved after the K-th task of the run (1-based)")
    transfer.add_argument("--paper-cases", action="store_true",
                          help="the paper's four cases of the run's domain one after the other (grid: room1to2 "
                               "after 2, room1to3 after 3 and 4, room3to4 after 4; cheetah and walker: Table 1); "
                               "finished ones are skipped, unfinished ones resumed")
    transfer.add_argument("--episodes", type=int, default=20, metavar="N", help="learner episodes (default 20)")
    transfer.add_argument("--few-shot-episodes", type=int, default=None, metavar="N",
                          help="read the few-shot score after N learner episodes (default 20, or --episodes if fewer)")
    transfer.add_argument("--eval-every", type=int, default=1, metavar="N",
                          help="evaluate after every N learner episodes (default 1)")
    transfer.add_argument("--reward", choices=("dense", "sparse"), default=None,
                          help="reward type (default: the run's transfer.reward if set, else the task's own; "
                               "test tasks sparse, training tasks dense)")
    transfer.add_argument("--learner-only", action="store_true",
                          help="turn the method's extras off (DRAGO: no reviewer, rehearsal or VAE updates)")
    transfer.add_argument("--out", type=Path, default=None,
                          help="transfer directory (with --paper-cases: the folder of the cases); "
                               "default RUN_DIR/transfer/TASK-afterK")
    transfer.add_argument("--force", action="store_true", help="overwrite an existing transfer directory")
    transfer.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")


def _cmd_transfer(args: argparse.Namespace) -> int:
    from drago.api import continue_with, new_transfer, run_paper_cases, run_transfer

    if args.paper_cases and (args.task is not None or args.after is not None):
        raise UsageError("--paper-cases chooses the tasks and stages itself; drop --task and --after")
    if not args.paper_cases and (args.task is None or args.after is None):
        raise UsageError("name the task and the stage, --task T --after K, or pass --paper-cases")
    options = {"episodes": args.episodes, "learner_only": args.learner_only,
               "few_shot_episodes": args.few_shot_episodes, "eval_every": args.eval_every,
               "dense_reward": None if args.reward is None else args.reward == "dense"}
    if args.paper_cases:
        # The same command skips finished cases and resumes the others; --force would redo every case.
        again = "again without --force" if args.force else "again"
        with continue_with(f"run the same `drago transfer --paper-cases` command {again} to continue"):
            run_paper_cases(args.run_dir, out=args.out, force=args.force, progress=not args.no_progress, **options)
        return 0
    trainer = new_transfer(args.run_dir, args.task, args.after, out=args.out, force=args.force,
                           progress=not args.no_progress, **options)
    trainer.logger.print(f"drago transfer {args.run_dir} --task {args.task} --after {args.after} -> {trainer.run_dir}")
    with continue_with(f"continue with `drago resume {trainer.run_dir}`"):
        run_transfer(trainer)
    return 0


COMMANDS["transfer"] = _cmd_transfer


# ---- drago report -----------------------------------------------------------------------------------
def _add_report_parser(sub) -> None:
    report = sub.add_parser(
        "report", help="one HTML page (and Markdown) with tables, curves and heatmaps of a set of runs",
        usage="drago report RUN_DIR [RUN_DIR ...] [--out DIR]",
        description="Groups the runs by method and writes DIR/report.html (self-contained) and DIR/report.md "
                    "with its figures. A folder that is not a run stands for the run directories below it. "
                    "Nothing is written into the runs.")
    report.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR")
    report.add_argument("--out", type=Path, default=Path("reports"), metavar="DIR",
                        help="output folder (default: reports)")


def _cmd_report(args: argparse.Namespace) -> int:
    from drago.api import build_report

    for path in build_report(args.run_dirs, args.out):
        print(f"wrote {path}")
    return 0


COMMANDS["report"] = _cmd_report


# ---- drago record -----------------------------------------------------------------------------------
def _add_record_parser(sub) -> None:
    record = sub.add_parser(
        "record", help="a finished run, its transfers and its evaluations as one small file to commit",
        usage="drago record RUN_DIR [--out FILE]",
        description="Makes every evaluation of the run's checkpoints (coverage, zero-shot returns and heatmap "
                    "cells on the grid, held-out retention on DeepMind Control), then writes the run's record: "
                    "its settings, provenance, logs, transfers and those evaluations, without checkpoints. "
                    "`drago report` and `drago study --records` read records as they read run directories.")
    record.add_argument("run_dir", type=Path, metavar="RUN_DIR")
    record.add_argument("--out", type=Path, default=None, metavar="FILE",
                        help="record file (default records/PRESET/METHOD/seedS.json.gz)")


def _cmd_record(args: argparse.Namespace) -> int:
    from drago.api import record_run

    path, record = record_run(args.run_dir, args.out)
    files = record["files"]
    print(f"recorded {args.run_dir} -> {path} ({path.stat().st_size / 1024:.0f} KiB, {len(files)} files, "
          f"protocol {record['protocol']['digest']})")
    return 0


COMMANDS["record"] = _cmd_record


# ---- drago study ------------------------------------------------------------------------------------
def _add_study_parser(sub) -> None:
    study = sub.add_parser(
        "study", help="the grid study in one command: methods x seeds, their transfer cases, one report",
        usage="drago study [PRESET] [--methods M ...] [--seeds S ...] [--out DIR] [--records DIR] [--jobs N] "
              "[--transfer-episodes N] [--transfer-eval-every N] [--transfer-few-shot-episodes N] [--cases TASK:K ...] "
              "[--transfer-reward R] [--no-transfer] "
              "[--dry-run | --status | --report-only] [--backend {local,slurm}] [--wait] [SLURM options] [key=value ...]",
        description="Runs every method x seed on the preset's sequence into OUT/METHOD/seedS, the paper's "
                    "transfer cases of each run (as `drago transfer --paper-cases`), then `drago report` into "
                    "OUT/report. Finished work is skipped and interrupted work resumed, so after any crash "
                    "the same command finishes the study. Prints the plan first. With --backend slurm the jobs "
                    "are SLURM batch jobs and the command returns once they are submitted.",
        epilog="key=value overrides apply to every run. A directory holding a run with other settings is an "
               "error: choose another --out or delete it.")
    study.add_argument("preset", nargs="?", default=None, help="preset of every run (default minigrid-cpu)")
    study.add_argument("--methods", nargs="+", default=None, metavar="M",
                       help="methods (default: drago continual ewc scratch replay drago-no-rehearsal "
                            "drago-no-reviewer)")
    study.add_argument("--seeds", nargs="+", default=None, metavar="S", help="seeds or ranges like 1-3 (default 1 2 3)")
    study.add_argument("--out", type=Path, default=None, metavar="DIR", help="study folder (default runs/study/PRESET)")
    study.add_argument("--jobs", type=int, default=None, metavar="N",
                       help="local: runs at a time, each with cores/N torch threads (default 1); slurm: the most "
                            "SLURM jobs of the study running at once (default: no cap)")
    study.add_argument("--transfer-episodes", type=int, default=None, metavar="N",
                       help="learner episodes of each transfer case (default 20)")
    study.add_argument("--transfer-eval-every", type=int, default=1, metavar="N",
                       help="evaluate each transfer after every N learner episodes (default 1; DeepMind Control "
                            "evaluations are costly, 5 still reads both few-shot scores)")
    study.add_argument("--transfer-few-shot-episodes", type=int, default=None, metavar="N",
                       help="read each transfer's few-shot score after N learner episodes (default 20, or "
                            "--transfer-episodes if fewer)")
    study.add_argument("--cases", nargs="+", default=None, metavar="TASK:K",
                       help="transfer cases instead of the paper's: TASK learned from the world model saved after "
                            "stage K, e.g. room1to2:2, or walker-run:4 to relearn a training task")
    study.add_argument("--transfer-reward", choices=("dense", "sparse"), default=None,
                       help="reward of the transfer cases (default: the run's transfer.reward, else the test task's "
                            "own, sparse on the grid); another one gets directories of its own, TASK-REWARD-afterK")
    study.add_argument("--no-transfer", action="store_true", help="sequence runs and report only")
    study.add_argument("--records", type=Path, default=None, metavar="DIR",
                       help="record each finished unit (a run, its transfers and evaluations) as "
                            "DIR/METHOD/seedS.json.gz, skip units recorded there with the study's protocol, and "
                            "build the report from the records (commit DIR to continue on another machine)")
    study.add_argument("--dry-run", action="store_true",
                       help="print the plan (with --backend slurm: the sbatch options of every job), run nothing")
    study.add_argument("--status", action="store_true",
                       help="what is queued, running, done and failed, from SLURM and the run directories; "
                            "runs nothing")
    study.add_argument("--report-only", action="store_true", help="write the report from what is on disk; runs nothing")
    study.add_argument("--backend", choices=("local", "slurm"), default="local",
                       help="local: child processes on this machine (default); slurm: SLURM batch jobs, "
                            "submitted with submitit (pip install -e '.[slurm]')")
    study.add_argument("--wait", action="store_true",
                       help="slurm: follow the jobs until they end, one line per finished job (the local "
                            "backend always does)")
    slurm = study.add_argument_group("SLURM options (--backend slurm; see docs: Running on a cluster)")
    slurm.add_argument("--partition", default=None, metavar="P", help="partition of every job")
    slurm.add_argument("--account", default=None, metavar="A", help="account to charge")
    slurm.add_argument("--qos", default=None, metavar="Q", help="quality of service")
    slurm.add_argument("--time", default=None, metavar="T",
                       help="time limit per job, minutes or [D-]HH:MM:SS (default 60); a job near it is "
                            "requeued and resumes from its last checkpoint")
    slurm.add_argument("--cpus", type=int, default=None, metavar="N",
                       help="CPUs per job (default 1); new runs get train.threads = N / runs per job")
    slurm.add_argument("--gpus", type=int, default=None, metavar="N",
                       help="GPUs per job (default 0); runs then get train.device=cuda, one GPU each")
    slurm.add_argument("--jobs-per-gpu", type=int, default=None, metavar="K",
                       help="runs sharing one GPU: a job with N GPUs runs N x K runs side by side (default 1)")
    slurm.add_argument("--mem", default=None, metavar="SIZE",
                       help="memory per job, e.g. 16G (default: the partition's)")
    slurm.add_argument("--sbatch", action="append", default=[], metavar="OPTIONS",
                       help="further sbatch options for every job, e.g. --sbatch='--constraint=a100 --exclude=n3' "
                            "(repeatable)")


def _cmd_study(args: argparse.Namespace) -> int:
    from drago.api import SLURM_OPTIONS, study_command

    overrides, preset = list(args.overrides), args.preset
    if preset is not None and "=" in preset:  # `drago study key=value`: no preset named
        overrides.insert(0, preset)
        preset = None
    # --methods/--seeds take every following word; key=value ones are overrides.
    methods = [m for m in args.methods or () if "=" not in m]
    seeds = [s for s in args.seeds or () if "=" not in s]
    overrides += [a for a in (*(args.methods or ()), *(args.seeds or ())) if "=" in a]
    if args.methods is not None and not methods:
        raise UsageError("--methods needs at least one method (see `drago list`)")
    if args.seeds is not None and not seeds:
        raise UsageError("--seeds needs at least one seed")
    modes = [flag for flag, on in (("--dry-run", args.dry_run), ("--status", args.status),
                                   ("--report-only", args.report_only)) if on]
    if len(modes) > 1:
        raise UsageError(f"{modes[0]} and {modes[1]} do not go together")
    outcome = study_command(
        preset, methods or None, seeds or None, out=args.out, overrides=overrides, jobs=args.jobs,
        transfers=not args.no_transfer, transfer_episodes=args.transfer_episodes,
        transfer_eval_every=args.transfer_eval_every, transfer_few_shot_episodes=args.transfer_few_shot_episodes,
        transfer_reward=args.transfer_reward, cases=args.cases, records=args.records,
        mode=modes[0][2:] if modes else "run", backend=args.backend, wait=args.wait,
        slurm={name: getattr(args, name) for name in SLURM_OPTIONS}, echo=lambda line: print(line, flush=True))
    if outcome.message is not None:
        print(outcome.message if outcome.ok else f"drago: {outcome.message}",
              file=sys.stdout if outcome.ok else sys.stderr)
    return 0 if outcome.ok else 1


COMMANDS["study"] = _cmd_study


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def _terminate_as_interrupt():
    """Make SIGTERM stop a command the way Ctrl-C does.

    A shell script that starts ``drago study ... &`` (or under ``nohup``) makes it ignore SIGINT, so
    ``kill PID`` (SIGTERM) is how such a job is stopped, and a study stops its own children that way too.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def main(argv: list[str] | None = None) -> int:
    # A drago command starts a Weights & Biases service of its own. W&B hands its service's address to child
    # processes in WANDB_SERVICE; were a run (a study's job, a resume after a crash) to use its parent's (a
    # notebook or script that used W&B), a run killed with SIGKILL would stay open in that service, which then
    # refuses the resumed process the same run id ("run ID ... is in use").
    os.environ.pop("WANDB_SERVICE", None)
    with _terminate_as_interrupt():
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    from drago.api import (CheckpointError, ConfigError, Interrupted, NonFiniteCheckpoint, RunDirError,
                           TrainingDiverged)

    try:
        args, extra = _parser().parse_known_args(argv)
        # Overrides may come before or after options; argparse alone keeps only the first group.
        unknown = [a for a in extra if a.startswith("-") or "=" not in a or args.command not in ("train", "study")]
        if unknown:
            raise UsageError(f"unrecognized arguments: {' '.join(unknown)}")
        args.overrides = extra
        return COMMANDS[args.command](args)
    except (UsageError, ConfigError, CheckpointError, RunDirError) as err:
        print(f"drago: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except (TrainingDiverged, NonFiniteCheckpoint) as err:
        print(f"drago: error: {err}", file=sys.stderr)
        return 1
    except Interrupted as interrupted:  # a command that says how it is continued
        print(f"drago: interrupted; {interrupted}", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # `drago list | head`: the reader left; say nothing more and do not flush into a closed pipe.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print("drago: interrupted; continue with `drago resume RUN_DIR`", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
