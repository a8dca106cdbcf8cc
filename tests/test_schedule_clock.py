"""``agent.schedule_clock``: what the agents' schedules count (docs: Reproducing the paper, "DRAGO's learner").

Under the official clock a DRAGO task's schedules count the reviewer's steps too, so its learner's CEM std
floor and learning rate fall twice as fast per learner episode as a reviewer-less method's; the learner
clock counts the learner's steps alone and changes nothing for a method without a reviewer.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import drago
from drago.agent.networks import linear_schedule

SMOKE = ["env.tasks=[room1,room2]", "train.steps_per_task=600", "agent.tdmpc.lr_schedule_steps=600"]


def _run(tmp_path: Path, method: str, clock: str) -> Path:
    cfg = drago.load_config("smoke", [*SMOKE, f"agent.schedule_clock={clock}"], method=method)
    return Path(drago.train(cfg, tmp_path / f"{method}-{clock}", progress=False).path)


@pytest.mark.slow
def test_the_learner_clock_changes_nothing_without_a_reviewer(tmp_path):
    task, learner = (_run(tmp_path, "continual", clock) for clock in ("task", "learner"))
    assert (task / "train.csv").read_text() == (learner / "train.csv").read_text()
    assert (task / "eval.csv").read_text() == (learner / "eval.csv").read_text()


@pytest.mark.slow
def test_under_the_learner_clock_drago_s_learner_floor_follows_its_own_steps(tmp_path):
    cfg = drago.load_config("smoke", SMOKE, method="drago").agent.tdmpc
    floors = {}
    for clock in ("task", "learner"):
        run = _run(tmp_path, "drago", clock)
        summary = json.loads((run / "summary.json").read_text())["tasks"][1]
        ckpt = torch.load(run / "checkpoints" / "task2_room2.pt", weights_only=False)
        # The last iteration's updates start where its clock stood before that iteration's episodes.
        episode = 100
        clock_at_last = (summary["learner_steps"] if clock == "learner" else summary["steps"]) - episode * (
            1 if clock == "learner" else 2)
        expected = linear_schedule(cfg.std_schedule_start, cfg.min_std, cfg.std_schedule_steps, clock_at_last + 9)
        assert ckpt["learner_std_floor"] == pytest.approx(expected)
        floors[clock] = ckpt["learner_std_floor"]
    assert floors["learner"] > floors["task"]  # the learner's exploration noise falls more slowly


@pytest.mark.parametrize("method, decides", [("continual", False), ("drago-no-reviewer", False), ("drago", True),
                                             ("drago-no-rehearsal", True)])
def test_the_clock_is_in_a_protocol_only_where_it_decides_something(method, decides):
    from drago.training.records import protocol_digest, run_protocol

    digests = {clock: protocol_digest(run_protocol(drago.load_config("smoke", [f"agent.schedule_clock={clock}"],
                                                                     method=method), {}, ["coverage"]))
               for clock in ("task", "learner")}
    assert (digests["task"] != digests["learner"]) == decides


@pytest.mark.parametrize("method, accepted", [("continual", True), ("drago", False)])
def test_a_study_takes_over_a_run_whose_clock_cannot_matter(method, accepted, tmp_path):
    from drago.study.plan import StudyError, plan_study
    from drago.training.rundir import write_run_config

    run_dir = tmp_path / method / "seed1"
    run_dir.mkdir(parents=True)
    write_run_config(run_dir, drago.load_config("smoke", ["agent.schedule_clock=task"], method=method, seed=1))
    plan = lambda: plan_study("smoke", [method], [1], out=tmp_path, overrides=["agent.schedule_clock=learner"],  # noqa: E731
                              transfers=False)
    if accepted:
        assert [job.label for job in plan().runs] == [f"{method} seed1"]
    else:
        with pytest.raises(StudyError, match="agent.schedule_clock: 'task' there, 'learner' here"):
            plan()
