"""`drago transfer`: a test task learned from the world model of a run's stage K (spec §4.2-4.3).

Sources are tiny `smoke` runs; transfers last one to three episodes of 100 steps.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import torch
import yaml

from drago import cli
from drago.agent.networks import WorldModel
from drago.config import Config
from drago.continual import METHODS
from drago.continual.drago import Drago
from drago.envs import task_optimum
from drago.train.checkpoint import load_checkpoint
from drago.train.transfer import PAPER_CASES

QUIET = ["--no-progress", "train.tensorboard=false"]
TWO_TASKS = "env.tasks=[room1,room2]"


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def transfer(source: Path, *args: str) -> int:
    return cli.main(["transfer", str(source), "--no-progress", *args])


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> dict[str, Path]:
    """Two-task smoke runs of DRAGO and of continual TD-MPC."""
    root = tmp_path_factory.mktemp("sources")
    out = {}
    for method in ("drago", "continual"):
        out[method] = root / method
        assert cli.main(["train", "smoke", "--method", method, "--out", str(out[method]), *QUIET, TWO_TASKS]) == 0
    return out


@pytest.fixture(scope="module")
def drago_transfer(sources) -> Path:
    """room1to2 after stage 2 of the DRAGO run, two learner episodes, reviewer on (the default)."""
    assert transfer(sources["drago"], "--task", "room1to2", "--after", "2", "--episodes", "2") == 0
    return sources["drago"] / "transfer" / "room1to2-after2"


# ---------------------------------------------------------------------------------------------------
# Outputs
# ---------------------------------------------------------------------------------------------------
def test_transfer_writes_a_run_directory_with_learning_curves(drago_transfer, sources):
    for name in ("config.yaml", "train.csv", "eval.csv", "timing.csv", "console.log", "summary.json",
                 "checkpoints/task1_room1to2.pt"):
        assert (drago_transfer / name).is_file(), name
    assert not (drago_transfer / "checkpoints" / "resume.pt").exists()

    cfg = Config.from_dict(yaml.safe_load((drago_transfer / "config.yaml").read_text()))
    assert cfg.env.tasks == ("room1to2",) and cfg.method.name == "drago"
    assert cfg.agent.seed_steps == 0 and cfg.train.learner_steps_per_task == 200
    assert cfg.transfer.after == 2 and cfg.transfer.learner_only is False
    source_ckpt = (drago_transfer / cfg.transfer.checkpoint).resolve()
    assert source_ckpt == (sources["drago"] / "checkpoints" / "task2_room2.pt").resolve()

    rows = read_csv(drago_transfer / "eval.csv")
    for column in ("episode", "learner_env_step", "env_step", "episode_reward", "optimal_return",
                   "fraction_of_optimal"):
        assert column in rows[0], column
    # An evaluation before the first episode and after every learner episode.
    assert [int(r["episode"]) for r in rows] == [0, 1, 2]
    assert [int(r["learner_env_step"]) for r in rows] == [0, 100, 200]
    # DRAGO's reviewer keeps running: one reviewer episode per learner episode, counted in env_step.
    assert [int(r["env_step"]) for r in rows] == [0, 200, 400]

    train_rows = read_csv(drago_transfer / "train.csv")
    assert len(train_rows) == 2
    assert all(r["reviewer_episode_reward"] != "" and r["rehearsal_loss"] != "" for r in train_rows)

    summary = json.loads((drago_transfer / "summary.json").read_text())
    t = summary["transfer"]
    assert summary["complete"] is True
    assert (t["task"], t["after"], t["method"], t["reward"]) == ("room1to2", 2, "drago", "sparse")
    assert t["learner_env_steps"] == 200 and t["total_env_steps"] == 400 and t["wall_time_s"] > 0
    # --few-shot-episodes defaults to --episodes when fewer than 20.
    assert t["few_shot_episodes"] == 2
    assert t["few_shot"]["equal_episodes"]["episode"] == 2
    # At equal env steps DRAGO is read after half the learner episodes: the rest went to the reviewer.
    assert t["few_shot"]["equal_env_steps"]["episode"] == 1
    assert t["few_shot"]["equal_env_steps"]["total_env_steps"] == 200
    assert t["final"]["return"] == float(rows[-1]["episode_reward"])


def test_test_tasks_use_sparse_reward_and_no_seed_phase(drago_transfer, sources):
    rows = read_csv(drago_transfer / "eval.csv")
    # The sparse optimum of room1to2 is 88.0 (spec §1.1.4); the dense one would be 266.5.
    assert float(rows[0]["optimal_return"]) == 88.0 == task_optimum("minigrid", "room1to2", False)
    # Updates start with the first episode (the source run's first two episodes were a seed phase).
    assert read_csv(drago_transfer / "train.csv")[0]["learner_total_loss"] != ""
    assert read_csv(sources["drago"] / "train.csv")[0]["learner_total_loss"] == ""


def test_relearning_a_training_task_uses_its_dense_reward(sources, tmp_path):
    out = tmp_path / "room1"
    assert transfer(sources["continual"], "--task", "room1", "--after", "2", "--episodes", "1", "--out", str(out)) == 0
    summary = json.loads((out / "summary.json").read_text())["transfer"]
    assert summary["reward"] == "dense" and summary["optimal_return"] == pytest.approx(250.9, abs=0.05)
    # Without a reviewer the learner spends every env step.
    assert summary["learner_env_steps"] == summary["total_env_steps"] == 100
    eq = summary["few_shot"]
    assert eq["equal_episodes"] == eq["equal_env_steps"] and eq["equal_episodes"]["episode"] == 1


def test_reward_can_be_chosen(sources, tmp_path):
    out = tmp_path / "dense"
    assert transfer(sources["continual"], "--task", "room1to2", "--after", "1", "--episodes", "1", "--reward", "dense",
                    "--out", str(out)) == 0
    assert json.loads((out / "summary.json").read_text())["transfer"]["reward"] == "dense"
    assert float(read_csv(out / "eval.csv")[0]["optimal_return"]) == pytest.approx(266.5, abs=0.05)


@pytest.mark.parametrize("case", ["continual", "drago-learner-only"])
def test_without_a_reviewer_total_env_steps_equal_learner_env_steps(sources, tmp_path, case):
    source = sources["continual" if case == "continual" else "drago"]
    extra = ["--learner-only"] if case == "drago-learner-only" else []
    out = tmp_path / case
    assert transfer(source, "--task", "room1to2", "--after", "2", "--episodes", "2", "--out", str(out), *extra) == 0
    rows = read_csv(out / "eval.csv")
    assert [int(r["env_step"]) for r in rows] == [int(r["learner_env_step"]) for r in rows] == [0, 100, 200]
    train_rows = read_csv(out / "train.csv")
    assert all(not r.get("reviewer_episode_reward") and not r.get("rehearsal_loss") for r in train_rows)
    cfg = Config.from_dict(yaml.safe_load((out / "config.yaml").read_text()))
    assert cfg.transfer.learner_only is bool(extra)
    summary = json.loads((out / "summary.json").read_text())["transfer"]
    assert summary["learner_only"] is bool(extra)
    assert summary["few_shot"]["equal_episodes"] == summary["few_shot"]["equal_env_steps"]


# ---------------------------------------------------------------------------------------------------
# What the test task starts from (spec §3.10: the world model, VAE and threshold; heads fresh)
# ---------------------------------------------------------------------------------------------------
class StartProbe(Drago):
    """DRAGO that records, per task, the state it begins with, before any update."""

    name = "start-probe"
    seen: dict[str, dict] = {}

    def begin_task(self, task):
        super().begin_task(task)
        obs = torch.tensor([[-0.5, -0.8, 0.0], [0.1, 0.2, 0.5], [0.6, -0.3, -1.0]])
        actions = torch.eye(3)
        with torch.no_grad():
            StartProbe.seen[task.name] = {
                "prediction": task.world_model(obs, actions).clone(),
                "reward": task.learner.heads.predict_reward(obs, actions).clone(),
                "vae": {k: v.clone() for k, v in self.vae.state_dict().items()},
                "threshold": self.threshold, "tasks_seen": self.tasks_seen,
                "reviewer": self.reviewer is not None, "dense": task.env.unwrapped.dense,
                "buffer": len(task.buffer), "step": task.step, "obs": obs, "actions": actions,
            }


@pytest.mark.parametrize("after", [1, 2])
def test_transfer_starts_from_the_stage_k_world_model_with_fresh_heads(tmp_path, monkeypatch, after):
    monkeypatch.setitem(METHODS, "start-probe", StartProbe)
    source = tmp_path / "source"
    assert cli.main(["train", "smoke", "--method", "start-probe", "--out", str(source), *QUIET, TWO_TASKS]) == 0
    assert transfer(source, "--task", "room1to2", "--after", str(after), "--episodes", "1") == 0
    seen = StartProbe.seen["room1to2"]
    ckpts = [load_checkpoint(source / "checkpoints" / f"task{k}_room{k}.pt", kind="task") for k in (1, 2)]
    ckpt = ckpts[after - 1]
    model = WorldModel(3, 3, 32, use_crelu=True, squash=True)
    model.load_state_dict(ckpt["world_model"])
    with torch.no_grad():
        assert torch.equal(seen["prediction"], model(seen["obs"], seen["actions"]))
        other = WorldModel(3, 3, 32, use_crelu=True, squash=True)
        other.load_state_dict(ckpts[2 - after]["world_model"])
        assert not torch.equal(seen["prediction"], other(seen["obs"], seen["actions"]))
    # Fresh heads: the reward head's last layer is zero-initialised, so it predicts exactly 0.
    assert torch.equal(seen["reward"], torch.zeros(3))
    # DRAGO's carried state is what the next task of the sequence would have received.
    assert seen["threshold"] == ckpt["method"]["threshold"] and seen["tasks_seen"] == after
    for key, value in ckpt["method"]["vae"].items():
        assert torch.equal(seen["vae"][key], value), key
    assert seen["reviewer"] is True and seen["dense"] is False
    assert seen["buffer"] == 0 and seen["step"] == 0


# ---------------------------------------------------------------------------------------------------
# Determinism and resume
# ---------------------------------------------------------------------------------------------------
def test_same_seed_gives_identical_transfer_logs(drago_transfer, sources, tmp_path):
    again = tmp_path / "again"
    assert transfer(sources["drago"], "--task", "room1to2", "--after", "2", "--episodes", "2", "--out", str(again)) == 0
    for name in ("train.csv", "eval.csv"):
        assert (again / name).read_bytes() == (drago_transfer / name).read_bytes(), name


def test_resume_after_a_crash_gives_the_uninterrupted_logs(sources, tmp_path, monkeypatch):
    args = ["--task", "room1to2", "--after", "2", "--episodes", "3"]
    reference, crashed = tmp_path / "reference", tmp_path / "crashed"
    assert transfer(sources["drago"], *args, "--out", str(reference)) == 0

    original = Drago.gradient_step
    calls = {"n": 0}

    def crash_in_the_third_iteration(self, task, u):
        calls["n"] += 1
        if calls["n"] == 25:  # 10 updates per iteration; resume.pt was written after iterations 1 and 2
            raise RuntimeError("simulated crash")
        return original(self, task, u)

    with monkeypatch.context() as m:
        m.setattr(Drago, "gradient_step", crash_in_the_third_iteration)
        with pytest.raises(RuntimeError, match="simulated crash"):
            transfer(sources["drago"], *args, "--out", str(crashed))
    assert load_checkpoint(crashed / "checkpoints" / "resume.pt", kind="resume")["episodes"] == 2
    assert not (crashed / "checkpoints" / "task1_room1to2.pt").exists()

    assert cli.main(["resume", str(crashed), "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv"):
        assert (crashed / name).read_bytes() == (reference / name).read_bytes(), name
    ours = json.loads((crashed / "summary.json").read_text())["transfer"]
    theirs = json.loads((reference / "summary.json").read_text())["transfer"]
    assert ours["few_shot"] == theirs["few_shot"] and ours["total_env_steps"] == theirs["total_env_steps"] == 600


def test_paper_cases_run_in_turn_skip_finished_ones_and_resume_unfinished_ones(tmp_path, monkeypatch, capsys):
    source = tmp_path / "source"
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(source), *QUIET]) == 0
    cases = [source / "transfer" / f"{task}-after{k}" for task, k in PAPER_CASES["minigrid"]]
    assert [c.name for c in cases] == ["room1to2-after2", "room1to3-after3", "room1to3-after4", "room3to4-after4"]
    args = ["--paper-cases", "--episodes", "2"]

    original = Drago.gradient_step
    calls = {"n": 0}

    def crash_in_the_second_case(self, task, u):
        if task.name == "room1to3":
            calls["n"] += 1
            if calls["n"] == 15:
                raise RuntimeError("simulated crash")
        return original(self, task, u)

    with monkeypatch.context() as m:
        m.setattr(Drago, "gradient_step", crash_in_the_second_case)
        with pytest.raises(RuntimeError, match="simulated crash"):
            transfer(source, *args)
    assert (cases[0] / "checkpoints" / "task1_room1to2.pt").is_file()
    assert (cases[1] / "checkpoints" / "resume.pt").is_file()
    assert not cases[2].exists() and not cases[3].exists()
    first = (cases[0] / "eval.csv").read_bytes()
    capsys.readouterr()

    assert transfer(source, *args) == 0
    out = capsys.readouterr().out
    assert "[room1to2 after 2] already finished" in out and "[room1to3 after 3] resuming" in out
    assert (cases[0] / "eval.csv").read_bytes() == first
    for case in cases:
        summary = json.loads((case / "summary.json").read_text())
        assert summary["complete"] is True and summary["transfer"]["few_shot"]["equal_episodes"]["episode"] == 2
    assert [json.loads((c / "summary.json").read_text())["transfer"]["after"] for c in cases] == [2, 3, 4, 4]

    # Other settings for existing cases are refused, not silently mixed.
    assert transfer(source, "--paper-cases", "--episodes", "3") == 2
    err = capsys.readouterr().err
    assert "other settings" in err and "--force" in err and len(err.strip().splitlines()) == 1


# ---------------------------------------------------------------------------------------------------
# One-line errors
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", ["unknown-task", "after-too-large", "after-zero", "stage-not-finished",
                                  "no-config", "episodes-zero", "exists", "missing-after", "paper-and-task"])
def test_transfer_errors_are_one_line(sources, drago_transfer, tmp_path, capsys, case):
    source = sources["drago"]
    args = ["--task", "room1to2", "--after", "2", "--episodes", "1", "--out", str(tmp_path / "t")]
    expected: tuple[str, ...]
    if case == "unknown-task":
        args[1] = "room9"
        expected = ("room9", "room1to2", "room3to4")
    elif case == "after-too-large":
        args[3] = "3"
        expected = ("--after 3", "2 tasks", "finished stages: 1, 2")
    elif case == "after-zero":
        args[3] = "0"
        expected = ("--after 0", "finished stages: 1, 2")
    elif case == "stage-not-finished":
        partial = tmp_path / "partial"
        (partial / "checkpoints").mkdir(parents=True)
        (partial / "config.yaml").write_bytes((source / "config.yaml").read_bytes())
        (partial / "checkpoints" / "task1_room1.pt").write_bytes(
            (source / "checkpoints" / "task1_room1.pt").read_bytes())
        source = partial
        expected = ("stage 2", "finished stages: 1")
    elif case == "no-config":
        source = tmp_path / "empty"
        source.mkdir()
        expected = ("config.yaml",)
    elif case == "episodes-zero":
        args[5] = "0"
        expected = ("--episodes", "positive")
    elif case == "exists":
        args = ["--task", "room1to2", "--after", "2", "--episodes", "2"]
        expected = ("already exists", "drago resume", "--force")
    elif case == "missing-after":
        args = ["--task", "room1to2"]
        expected = ("--after",)
    else:
        args = ["--paper-cases", "--task", "room1to2"]
        expected = ("--paper-cases",)
    capsys.readouterr()
    assert transfer(source, *args) == 2
    err = capsys.readouterr().err.strip()
    print(err)
    assert err.startswith("drago: error: ") and len(err.splitlines()) == 1 and "Traceback" not in err
    for text in expected:
        assert text in err, text
