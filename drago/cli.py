"""The ``drago`` command: parses, validates, calls the library. No logic of its own.

Every user error ends as one line ``drago: error: ...`` on stderr with exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
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
                           epilog="key=value overrides any setting, e.g. agent.mlp_dim=256 (see `drago list --settings`)")
    train.add_argument("preset", help="preset name (see `drago list`)")
    train.add_argument("--method", default=None, help="continual method (default: the preset's, continual)")
    train.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's, 1)")
    train.add_argument("--out", type=Path, default=None, help="run directory (default runs/PRESET/METHOD/seedS)")
    train.add_argument("--force", action="store_true", help="overwrite an existing run directory")
    train.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")

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
    _add_transfer_parser(sub)
    _add_report_parser(sub)
    return parser


def _cmd_train(args: argparse.Namespace) -> int:
    from drago.config import load_config
    from drago.train.run import default_run_dir, new_run

    if args.seed is not None and args.seed < 0:
        raise UsageError(f"--seed must be a non-negative integer, got {args.seed}")
    cfg = load_config(args.preset, args.overrides, method=args.method, seed=args.seed)
    run_dir = args.out or default_run_dir(cfg)
    trainer = new_run(cfg, run_dir, force=args.force, progress=not args.no_progress)
    trainer.logger.print(f"drago train {cfg.preset} --method {cfg.method.name} --seed {cfg.train.seed} -> {run_dir}")
    trainer.run()
    return 0


def _cmd_resume(args: argparse.Namespace) -> int:
    from drago.train.run import resume

    trainer = resume(args.run_dir, progress=not args.no_progress)
    done = trainer.completed_tasks()
    if done == len(trainer.cfg.env.tasks):
        trainer.logger.print(f"{args.run_dir} is already complete ({done} tasks); nothing to do")
        trainer.write_summary()
        return 0
    trainer.logger.print(f"resuming {args.run_dir}: {done} of {len(trainer.cfg.env.tasks)} tasks complete")
    trainer.run()
    return 0


def _cmd_list(args: argparse.Namespace) -> int:
    from drago.config import available_presets, describe_settings
    from drago.continual import METHODS
    from drago.envs import GRID_SEQUENCES, GRID_TASKS

    print("presets:  " + ", ".join(available_presets()))
    print("methods:")
    for name, cls in METHODS.items():
        print(f"  {name:<20} {cls.description}")
    print("tasks (minigrid):")
    for name, task in GRID_TASKS.items():
        reward = "dense" if task.dense else "sparse"
        print(f"  {name:<20} {task.start} -> {task.goal}, {reward}: {task.description}")
    print("sequences:  " + "; ".join(f"{k}: {' -> '.join(v)}" for k, v in GRID_SEQUENCES.items()))
    if args.settings:
        print("settings (key, type, default):")
        for key, kind, default in describe_settings():
            print(f"  {key:<34} {kind:<18} {default}")
    return 0


def _cmd_eval_coverage(args: argparse.Namespace) -> int:
    from drago.eval.coverage import COVERAGE_FILE, coverage_of_run, format_table, run_checkpoints, write_coverage_csv

    # Check every run before evaluating any, so a typo in the last argument fails at once.
    for run_dir in args.run_dirs:
        run_checkpoints(run_dir)
    rows = []
    for run_dir in args.run_dirs:
        run_rows = coverage_of_run(run_dir)
        write_coverage_csv(run_rows, run_dir / COVERAGE_FILE)
        rows.extend(run_rows)
    print("exact-match accuracy of the world model after each task:")
    for line in format_table(rows):
        print(line)
    for run_dir in args.run_dirs:
        print(f"wrote {run_dir / COVERAGE_FILE}")
    if args.out is not None:
        print(f"wrote {write_coverage_csv(rows, args.out)}")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    return {"coverage": _cmd_eval_coverage}[args.eval_command](args)


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
    transfer.add_argument("--task", default=None, help="task to learn (a test task, or a training task to relearn)")
    transfer.add_argument("--after", type=int, default=None, metavar="K",
                          help="use the world model saved after the K-th task of the run (1-based)")
    transfer.add_argument("--paper-cases", action="store_true",
                          help="the paper's four grid cases one after the other (room1to2 after 2, room1to3 after 3 "
                               "and 4, room3to4 after 4); finished ones are skipped, unfinished ones resumed")
    transfer.add_argument("--episodes", type=int, default=20, metavar="N", help="learner episodes (default 20)")
    transfer.add_argument("--few-shot-episodes", type=int, default=None, metavar="N",
                          help="read the few-shot score after N learner episodes (default 20, or --episodes if fewer)")
    transfer.add_argument("--eval-every", type=int, default=1, metavar="N",
                          help="evaluate after every N learner episodes (default 1)")
    transfer.add_argument("--reward", choices=("dense", "sparse"), default=None,
                          help="reward type (default: the task's own; test tasks sparse, training tasks dense)")
    transfer.add_argument("--learner-only", action="store_true",
                          help="turn the method's extras off (DRAGO: no reviewer, rehearsal or VAE updates)")
    transfer.add_argument("--out", type=Path, default=None,
                          help="transfer directory (with --paper-cases: the folder of the cases); "
                               "default RUN_DIR/transfer/TASK-afterK")
    transfer.add_argument("--force", action="store_true", help="overwrite an existing transfer directory")
    transfer.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")


def _cmd_transfer(args: argparse.Namespace) -> int:
    from drago.train.transfer import new_transfer, run_paper_cases, run_transfer

    if args.paper_cases and (args.task is not None or args.after is not None):
        raise UsageError("--paper-cases chooses the tasks and stages itself; drop --task and --after")
    if not args.paper_cases and (args.task is None or args.after is None):
        raise UsageError("name the task and the stage, --task T --after K, or pass --paper-cases")
    options = {"episodes": args.episodes, "learner_only": args.learner_only,
               "few_shot_episodes": args.few_shot_episodes, "eval_every": args.eval_every,
               "dense_reward": None if args.reward is None else args.reward == "dense"}
    if args.paper_cases:
        run_paper_cases(args.run_dir, out=args.out, force=args.force, progress=not args.no_progress, **options)
        return 0
    trainer = new_transfer(args.run_dir, args.task, args.after, out=args.out, force=args.force,
                           progress=not args.no_progress, **options)
    trainer.logger.print(f"drago transfer {args.run_dir} --task {args.task} --after {args.after} -> {trainer.run_dir}")
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
    from drago.eval.report import build_report

    for path in build_report(args.run_dirs, args.out):
        print(f"wrote {path}")
    return 0


COMMANDS["report"] = _cmd_report


def main(argv: list[str] | None = None) -> int:
    from drago.config import ConfigError
    from drago.train.checkpoint import CheckpointError
    from drago.train.run import RunDirError

    try:
        args, extra = _parser().parse_known_args(argv)
        # Overrides may come before or after options; argparse alone keeps only the first group.
        unknown = [a for a in extra if a.startswith("-") or "=" not in a or args.command != "train"]
        if unknown:
            raise UsageError(f"unrecognized arguments: {' '.join(unknown)}")
        args.overrides = extra
        return COMMANDS[args.command](args)
    except (UsageError, ConfigError, CheckpointError, RunDirError) as err:
        print(f"drago: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:
        # `drago list | head`: the reader left; say nothing more and do not flush into a closed pipe.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print("drago: interrupted; continue with `drago resume RUN_DIR`", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
