"""Branch a run after its stage K: a new run directory holding its first K task checkpoints and logs, whose
next tasks train under other settings, for asking "what if from here on ..." without retraining the stages
before (a diagnosis, not a study: a branch's earlier stages come from the source's settings).

    .venv/bin/python scripts/branch_run.py SOURCE_RUN --after 2 --out BRANCH [--tasks room3] \\
        [train.seed=4 agent.schedule_clock=learner ...]
    .venv/bin/drago resume BRANCH

``--tasks`` names the tasks after stage K the branch trains (default: the source's). A changed
``train.seed`` gives the branch's next tasks other random streams over the same stage-K world model.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from drago.config import apply_override, validate
from drago.training.rundir import read_run_config, task_checkpoint_path, write_run_config

LOGS = ("train.csv", "eval.csv", "timing.csv", "visitation.csv", "console.log")


def branch(source: Path, after: int, out: Path, overrides: list[str], tasks: list[str] | None) -> Path:
    cfg = read_run_config(source)
    done = list(cfg.env.tasks[:after])
    if len(done) < after or not all(task_checkpoint_path(source, cfg.env.tasks, k).exists()
                                    for k in range(1, after + 1)):
        raise SystemExit(f"{source} has not finished stage {after}")
    if out.exists():
        raise SystemExit(f"{out} exists; choose another --out")
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep:
            raise SystemExit(f"override {item!r} is not key=value")
        apply_override(cfg, key, raw)
    cfg.env.tasks = tuple(done + (tasks if tasks is not None else list(cfg.env.tasks[after:])))
    validate(cfg)
    (out / "checkpoints").mkdir(parents=True)
    for k in range(1, after + 1):
        shutil.copy2(task_checkpoint_path(source, cfg.env.tasks, k), out / "checkpoints")
    # The trainer cuts each log back to where stage K ended (the positions its checkpoint holds).
    for name in LOGS:
        if (source / name).exists():
            shutil.copy2(source / name, out / name)
    write_run_config(out, cfg)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path)
    parser.add_argument("--after", type=int, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--tasks", nargs="+")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_intermixed_args(argv)
    print(branch(args.source, args.after, args.out, args.overrides, args.tasks))
    return 0


if __name__ == "__main__":
    sys.exit(main())
