"""drago from Python, end to end, in about a minute on a CPU: configure, train, read, evaluate, report.

    .venv/bin/python examples/api_tour.py [OUT_DIR]
"""

from __future__ import annotations

import sys
from pathlib import Path

import drago

out = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/api-tour")

# 1. A config: a packaged preset (or a path to your own YAML file) plus key=value overrides.
cfg = drago.load_config("smoke", ["env.tasks=[room1,room2]"], method="drago")

# 2. Train the two-room sequence; an interrupted run continues with drago.resume(path).run().
run = drago.train(cfg, out=out / "drago", force=True, progress=False)

# 3. Read it back: per-task results, logs, checkpoints, world models.
print(run)
for task in run.tasks:
    print(f"  {task['name']}: final return {task['final_eval_return']:.1f} "
          f"({task['fraction_of_optimal']:.0%} of the DP optimum) in {task['wall_time_s']:.0f} s")
log = run.metrics("eval", as_frame=False)
print(f"  {len(log['env_step'])} evaluations logged; last return {log['episode_reward'][-1]:.1f}")

# 4. What the world model still knows: exact-match accuracy of its predictions in each room, per stage.
for row in drago.coverage(run.path):
    if row["room"] in ("room1", "room2"):
        print(f"  after stage {row['stage']} ({row['stage_task']}): {row['room']} accuracy {row['accuracy']:.2f}")

# 5. A test task learned from the stage-2 world model, and one report over everything.
transfer = drago.new_transfer(run.path, "room1to2", 2, episodes=2, progress=False)
drago.run_transfer(transfer)
for path in drago.build_report([run.path], out / "report"):
    print(f"wrote {path}")
