"""Where each agent went: per-cell visits of the learner, DRAGO's reviewer and a uniformly random agent."""

from __future__ import annotations

import csv
from collections import Counter

import numpy as np
import pytest
from helpers import QUIET

from drago import cli
from drago.envs.fourrooms import is_traversable, observation
from drago.envs.tasks import GRID_TASKS
from drago.report import build_report
from drago.training.visitation import read_visitation, visit_counts


def test_visit_counts_decode_cells_as_the_environment_encodes_them():
    cells = [(1, 1), (1, 1), (25, 25), (13, 13), (7, 20)]
    obs = np.stack([observation(cell, heading) for cell, heading in zip(cells, (0, 3, 1, 2, 0))])
    counts = visit_counts(obs + np.float32(0.01))  # a little noise decodes to the same cell
    assert counts.sum() == 5 and counts[1, 1] == 2 and counts[25, 25] == 1 and counts[13, 13] == 1
    assert counts[20, 7] == 1  # indexed [y, x]


def test_a_drago_run_records_each_agents_visits_per_task(tmp_path):
    out = tmp_path / "run"
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(out), *QUIET, "env.tasks=[room1,room2]",
                     "train.learner_steps_per_task=400", "train.reviewer_steps_per_task=200"]) == 0
    rows = read_visitation(out / "visitation.csv")
    steps = Counter()
    for row in rows:
        assert is_traversable((int(row["x"]), int(row["y"]))) and int(row["visits"]) > 0
        steps[(int(row["stage"]), row["task"], row["agent"])] += int(row["visits"])
    # Task 1 has no reviewer: the random reference takes the learner's steps; task 2 the reviewer's.
    assert steps == {(1, "room1", "learner"): 400, (1, "room1", "random"): 400,
                     (2, "room2", "learner"): 400, (2, "room2", "reviewer"): 200, (2, "room2", "random"): 200}
    # Every episode starts on the task's start cell: the learner's four episodes of room 1 visit it four times at least.
    first = {(int(r["x"]), int(r["y"])): int(r["visits"]) for r in rows if r["stage"] == "1" and r["agent"] == "learner"}
    assert first[tuple(GRID_TASKS["room1"].start)] >= 4
    with (out / "visitation.csv").open() as f:
        assert next(csv.reader(f)) == ["stage", "task", "agent", "x", "y", "visits"]

    # The report: each agent's share of steps per room (they sum to 1) and the reviewer's maps.
    html, md = build_report([out], tmp_path / "report")
    assert (tmp_path / "report" / "visitation.png").is_file()
    table = md.read_text().split("## Where the agents go")[1].split("\n## ")[0]
    reviewer = next(line for line in table.splitlines() if "| reviewer |" in line)
    cells = [c.strip() for c in reviewer.strip("|").split("|")]
    assert cells[:5] == ["drago", "2: room2", "reviewer", "1", "200"]
    assert sum(float(c) for c in cells[5:]) == pytest.approx(1.0, abs=0.03)  # five shares rounded to 0.01
    assert "Where the reviewer goes" in html.read_text()
    # The runs table states what each agent spent: the learner's 400 + 400 env steps, the reviewer's 200 on top.
    runs = md.read_text().split("## Runs")[1].split("\n## ")[0]
    row = [c.strip() for c in next(line for line in runs.splitlines() if line.startswith("| drago")).strip("|").split("|")]
    assert row[5:7] == ["800", "1,000"]
