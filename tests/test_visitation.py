"""Where each agent went (per-cell visits of the learner, DRAGO's reviewer and a uniformly random agent) and what
DRAGO's reviewer is paid on every transition of the grid."""

from __future__ import annotations

import csv
import shutil
from collections import Counter

import numpy as np
import pytest
from helpers import QUIET

from drago import cli
from drago.envs.fourrooms import is_traversable, observation
from drago.envs.tasks import GRID_TASKS
from drago.config import ConfigError
from drago.eval.coverage import grid_coverage, grid_transitions
from drago.eval.predictor import load_world_model
from drago.eval.reviewer_pay import PAID, pays_a_reviewer, reviewer_pay_of_run
from drago.report import build_report
from drago.training.checkpoint import load_task_checkpoint
from drago.training.visitation import read_visitation, visit_counts


@pytest.fixture(scope="module")
def drago_run(tmp_path_factory):
    """Two rooms of DRAGO with separate budgets: 400 learner steps a task, 200 reviewer steps in task 2."""
    out = tmp_path_factory.mktemp("drago") / "run"
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(out), *QUIET, "env.tasks=[room1,room2]",
                     "train.learner_steps_per_task=400", "train.reviewer_steps_per_task=200"]) == 0
    return out


def test_visit_counts_decode_cells_as_the_environment_encodes_them():
    cells = [(1, 1), (1, 1), (25, 25), (13, 13), (7, 20)]
    obs = np.stack([observation(cell, heading) for cell, heading in zip(cells, (0, 3, 1, 2, 0))])
    counts = visit_counts(obs + np.float32(0.01))  # a little noise decodes to the same cell
    assert counts.sum() == 5 and counts[1, 1] == 2 and counts[25, 25] == 1 and counts[13, 13] == 1
    assert counts[20, 7] == 1  # indexed [y, x]


@pytest.mark.slow
def test_a_drago_run_records_each_agents_visits_per_task(drago_run, tmp_path):
    out = drago_run
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


@pytest.mark.slow
def test_the_reviewers_pay_is_the_intrinsic_reward_of_the_old_models_predictions(drago_run, tmp_path):
    """r_old = sigmoid(4(score - theta)), c = sigmoid(score - theta), r = r_old - 0.5 c (paper §3.2, the official
    code's form), with score = -log(MSE + eps) of the stage's model as coverage computes it on its own."""
    checkpoint = drago_run / "checkpoints" / "task1_room1.pt"
    pays = reviewer_pay_of_run(drago_run)
    assert [(pay.stage, pay.task, pay.next_task) for pay in pays] == [(1, "room1", "room2")]  # no task after room2
    pay = pays[0]
    assert pay.threshold == load_task_checkpoint(checkpoint).data["method"]["threshold"]
    score = grid_coverage(load_world_model(checkpoint)).score
    sigmoid = lambda x: 1.0 / (1.0 + np.exp(-x))  # noqa: E731
    np.testing.assert_allclose(pay.old_term, sigmoid(4.0 * (score - pay.threshold)), atol=1e-4)
    np.testing.assert_allclose(pay.cost, sigmoid(score - pay.threshold), atol=1e-4)
    np.testing.assert_allclose(pay.reward, pay.old_term - 0.5 * pay.cost, atol=1e-6)
    assert pay.rooms["all"]["paid"] == pytest.approx(float((pay.old_term > PAID).mean()))

    html, md = build_report([drago_run], tmp_path / "report")
    assert (tmp_path / "report" / "reviewer-pay.png").is_file() and "Where the reviewer is paid" in html.read_text()
    # What the reviewer earned, episode by episode: drawn from task 2's reviewer rows of train.csv.
    assert (tmp_path / "report" / "reviewer-reward.png").is_file() and "What the reviewer earned" in html.read_text()
    table = md.read_text().split("## What the reviewer is paid")[1].split("\n## ")[0]
    row = [c.strip() for c in next(line for line in table.splitlines() if line.startswith("| drago")).strip("|").split("|")]
    assert row[:5] == ["drago", "1: room1", "room2", "1", f"{pay.threshold:.2f}"]
    assert row[5] == f"{pay.rooms['room1']['paid']:.2f}"  # the old rooms after task 1: room 1


@pytest.mark.slow
def test_what_the_reviewer_would_have_been_paid_under_the_papers_form_or_another_theta(drago_run):
    """The paper's form on the same checkpoint: r_old = sigmoid(-log mean|err|) = 1 / (1 + mean|err|), and at a
    task's start (current model = old model) r = (1 - 0.5) r_old; another theta shifts the code's sigmoid."""
    checkpoint = drago_run / "checkpoints" / "task1_room1.pt"
    coverage = grid_coverage(load_world_model(checkpoint))
    mean_abs_error = np.abs(coverage.predicted - grid_transitions()[2]).mean(-1)
    paper = reviewer_pay_of_run(drago_run, variant="paper")[0]
    np.testing.assert_allclose(paper.old_term, 1.0 / (1.0 + mean_abs_error), atol=1e-4)
    np.testing.assert_allclose(paper.reward, 0.5 * paper.old_term, atol=1e-6)

    shifted = reviewer_pay_of_run(drago_run, threshold=7.25)[0]
    sigmoid = lambda x: 1.0 / (1.0 + np.exp(-x))  # noqa: E731
    assert shifted.threshold == 7.25
    np.testing.assert_allclose(shifted.old_term, sigmoid(4.0 * (coverage.score - 7.25)), atol=1e-4)
    with pytest.raises(ConfigError, match="valid: code, paper"):
        reviewer_pay_of_run(drago_run, variant="papr")


@pytest.mark.slow
def test_a_runs_threshold_offset_is_in_what_its_reviewer_is_paid(drago_run, tmp_path):
    run = tmp_path / "offset"
    shutil.copytree(drago_run, run)
    config = run / "config.yaml"
    config.write_text(config.read_text().replace("threshold_offset: 0.0", "threshold_offset: 2.5"))
    saved = load_task_checkpoint(run / "checkpoints" / "task1_room1.pt").data["method"]["threshold"]
    assert reviewer_pay_of_run(run)[0].threshold == pytest.approx(saved - 2.5)


def test_only_methods_with_a_reviewers_reward_are_paid():
    assert pays_a_reviewer("drago") and pays_a_reviewer("drago-no-rehearsal")
    assert not pays_a_reviewer("continual") and not pays_a_reviewer("drago-no-reviewer")
    assert not pays_a_reviewer("a-plugin-that-is-not-installed")
