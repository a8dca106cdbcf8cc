"""What a study unit costs: where the seconds of one grid unit go, from its record's own timings.

A unit is one run with its four transfer cases and the evaluations made from its checkpoints
(docs: Command line, "Records"). Its record already says how long each part took: ``timing.csv`` splits
every training iteration into acting (the learner's episode and, for DRAGO, the reviewer's, counted in
``collect_s``), gradient updates (``update_s``) and evaluation episodes (``eval_s``); what a task's wall time
holds beyond these is checkpoints, logging and the task's set-up. The transfers' own summaries and timings
give theirs, and the record's ``evaluation_cpu_s`` the CPU seconds of each evaluation.

The updates of a DRAGO task are several things at once (the learner's and the reviewer's updates, the
intrinsic reward, the VAE and rehearsal). ``--split`` measures their shares on this machine: it trains a
short DRAGO sequence of two rooms in this process, one thread, timing each part of every gradient step of
the second task (the one with a reviewer and rehearsal) by wrapping the methods that do them; the shares
are then applied to the record's update seconds of DRAGO's tasks after the first.

    .venv/bin/python benchmarks/unit_cost.py RECORD [--split] [--split-steps 3000] [--out CSV]

Not part of the test suite. It prints the date, the command, the commit and the CPU; the CSV holds the
table only. The seconds are those of the machine that made the record (its provenance names the CPU), and
of its threads: a study with ``--jobs 2`` on 2 cores ran each unit on one thread beside another unit.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import io
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from zero_shot_ceiling import commit  # noqa: E402  (benchmarks/ is the script's folder)

from drago.training.records import cpu_model, read_record
from drago.training.rundir import write_rows_csv

COLUMNS = ("part", "seconds", "share", "how")


def _rows(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def breakdown(record: dict, update_shares: dict[str, float] | None) -> list[dict]:
    """The unit's wall seconds by part (CPU seconds for the evaluations, which record only those)."""
    files = record["files"]
    summary = json.loads(files["summary.json"])
    method = record["unit"]["method"]
    parts: dict[str, float] = defaultdict(float)
    how: dict[str, str] = {}
    timing = _rows(files.get("timing.csv", ""))
    for task in summary["tasks"]:
        rows = [r for r in timing if r["task"] == task["name"]]
        collect = sum(float(r["collect_s"]) for r in rows)
        update = sum(float(r["update_s"]) for r in rows)
        evaluate = sum(float(r["eval_s"]) for r in rows)
        parts["acting (learner and reviewer episodes)"] += collect
        parts["evaluation episodes"] += evaluate
        parts["checkpoints, logging, task set-up"] += max(0.0, float(task["wall_time_s"]) - collect - update - evaluate)
        if update_shares and method.startswith("drago") and int(task["index"]) > 0:
            for name, share in update_shares.items():
                parts[f"updates: {name}"] += update * share
        else:
            parts["updates: learner (and VAE on DRAGO's first task)"] += update
    for name in files:
        if name.startswith("transfer/") and name.endswith("/summary.json") and name.count("/") == 2:
            case = name.rsplit("/", 1)[0]
            wall = float(json.loads(files[name])["wall_time_s"])
            rows = _rows(files.get(f"{case}/timing.csv", ""))
            split = {key: sum(float(r[key]) for r in rows) for key in ("collect_s", "update_s", "eval_s")}
            parts["transfers: updates"] += split["update_s"]
            parts["transfers: acting"] += split["collect_s"]
            parts["transfers: evaluation episodes (after every learner episode)"] += split["eval_s"]
            parts["transfers: checkpoints, logging, set-up"] += max(0.0, wall - sum(split.values()))
    for name, seconds in (record.get("evaluation_cpu_s") or {}).items():
        parts[f"evaluation from checkpoints: {name}"] += float(seconds)
        how[f"evaluation from checkpoints: {name}"] = "CPU s"
    total = sum(parts.values())
    return [{"part": part, "seconds": round(seconds, 1), "share": round(seconds / total, 4),
             "how": how.get(part, "wall s")} for part, seconds in sorted(parts.items(), key=lambda kv: -kv[1])]


def measure_update_shares(steps: int) -> dict[str, float]:
    """Shares of a DRAGO gradient step (second task) by part, measured on a short two-room run."""
    import torch

    import drago
    from drago.agent.agent import Agent
    from drago.continual import drago as drago_method

    torch.set_num_threads(1)
    spent: dict[str, float] = defaultdict(float)
    active = {"on": False}

    def timed(name, function):
        def wrapper(*args, **kwargs):
            if not active["on"]:
                return function(*args, **kwargs)
            started = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                key = name(args) if callable(name) else name
                spent[key] += time.process_time() - started
        return wrapper

    cls = drago_method.Drago
    originals = {"update": Agent.update, "rollout": Agent.rollout, "gradient_step": cls.gradient_step,
                 "_relabel": cls._relabel, "_vae_step": cls._vae_step, "_rehearsal": cls._rehearsal}

    def gradient_step(self, task, u):
        active["on"] = task.index > 0  # the second task: reviewer, rehearsal and relabelling all at work
        return timed("whole gradient step", originals["gradient_step"])(self, task, u)

    Agent.update = timed(lambda a: "reviewer update" if a[0].reviewer else "learner update", originals["update"])
    Agent.rollout = timed("shared world-model rollout", originals["rollout"])
    cls.gradient_step = gradient_step
    cls._relabel = timed("intrinsic reward (old and current model)", originals["_relabel"])
    cls._vae_step = timed("VAE", originals["_vae_step"])
    cls._rehearsal = timed("rehearsal loss (synthetic batch, old model's labels)", originals["_rehearsal"])
    try:
        short = [f"train.steps_per_task={steps}", f"agent.seed_steps={steps // 5}", "env.tasks=[room1,room2]",
                 "train.threads=1", "train.tensorboard=false", f"train.reviewer_steps_per_task={steps // 2}",
                 f"train.eval_freq={steps}", f"train.checkpoint_freq={steps}"]
        cfg = drago.load_config("minigrid-cpu", short, method="drago", seed=1)
        with tempfile.TemporaryDirectory() as folder:
            drago.train(cfg, out=Path(folder) / "run", progress=False)
    finally:
        Agent.update, Agent.rollout = originals["update"], originals["rollout"]
        for name in ("gradient_step", "_relabel", "_vae_step", "_rehearsal"):
            setattr(cls, name, originals[name])
    whole = spent.pop("whole gradient step")
    parts = dict(spent)
    parts["rehearsal backward and step, sampling, priorities"] = max(0.0, whole - sum(parts.values()))
    return {name: seconds / whole for name, seconds in parts.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("record", type=Path)
    parser.add_argument("--split", action="store_true", help="measure the shares of DRAGO's gradient step here")
    parser.add_argument("--split-steps", type=int, default=3000, help="steps per task of the measuring run")
    parser.add_argument("--out", type=Path, default=None, help="CSV of the table")
    args = parser.parse_args()
    record = read_record(args.record)
    print(f"# {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, commit {commit()}, CPU {cpu_model()}")
    print(f"# {' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}")
    prov = record["provenance"]
    print(f"# the record: {record['unit']['method']} seed {record['unit']['seed']}, recorded {prov['recorded']} "
          f"on {prov['cpu']} with {prov['threads']} thread(s), commit {str(prov['commit'])[:12]}")
    shares = measure_update_shares(args.split_steps) if args.split else None
    if shares:
        print("shares of a DRAGO gradient step (second task), measured here:")
        for name, share in sorted(shares.items(), key=lambda kv: -kv[1]):
            print(f"  {name:<55} {share:6.1%}")
    rows = breakdown(record, shares)
    total = sum(r["seconds"] for r in rows)
    print(f"{'part':<60} {'seconds':>9} {'share':>7}  measure")
    for row in rows:
        print(f"{row['part']:<60} {row['seconds']:>9.1f} {row['share']:>7.1%}  {row['how']}")
    print(f"{'total':<60} {total:>9.1f}")
    if args.out:
        write_rows_csv(rows, COLUMNS, args.out)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
