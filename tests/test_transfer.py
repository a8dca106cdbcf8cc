"""`drago transfer`: a test task learned from the world model of a run's stage K (paper §4.4).

Sources are tiny `smoke` runs; transfers last one to three episodes of 100 steps.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from drago import cli
from drago.agent.networks import WorldModel
from drago.config import Config
from drago.continual import METHODS
from drago.continual.drago import Drago
from drago.envs import task_optimum
from drago.training.checkpoint import load_checkpoint
from drago.training.rundir import read_run_config
from drago.training.transfer import paper_cases, reward_variant
from helpers import QUIET, SimulatedCrash, crash_at_gradient_step, read_csv

# Every test here transfers from runs it trains first.
pytestmark = pytest.mark.slow

TWO_TASKS = "env.tasks=[room1,room2]"


def transfer(source: Path, *args: str) -> int:
    return cli.main(["transfer", str(source), "--no-progress", *args])


@pytest.fixture(scope="module")
def sources(smoke_runs) -> dict[str, Path]:
    """Two-task smoke runs of DRAGO and of continual TD-MPC."""
    return {method: smoke_runs(method, TWO_TASKS) for method in ("drago", "continual")}


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
    # The sparse optimum of room1to2 is 88.0 (paper Appendix C); the dense one would be 266.5.
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


def test_a_transfer_with_another_reward_gets_a_directory_of_its_own(smoke_runs):
    source = smoke_runs("continual", TWO_TASKS)
    assert transfer(source, "--task", "room1to2", "--after", "1", "--episodes", "1") == 0
    assert transfer(source, "--task", "room1to2", "--after", "1", "--episodes", "1", "--reward", "dense") == 0
    own, dense = source / "transfer" / "room1to2-after1", source / "transfer" / "room1to2-dense-after1"
    assert [json.loads((d / "summary.json").read_text())["transfer"]["reward"] for d in (own, dense)] == ["sparse", "dense"]
    cfg = read_run_config(source)
    # Asking for the task's own reward is no variant; a training room's own reward is dense.
    assert reward_variant(cfg, "room1to2", False) is None and reward_variant(cfg, "room1", True) is None
    assert reward_variant(cfg, "room1", False) == "sparse" and reward_variant(cfg, "room1to2", None) is None


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
# What the test task starts from (paper §3.3; docs: Design, how a run flows: the world model, VAE and threshold; heads fresh)
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
                "reviewer": self.task_parts(task).reviewer is not None, "dense": task.env.unwrapped.dense,
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


def test_resume_after_a_crash_gives_the_uninterrupted_logs(sources, tmp_path):
    args = ["--task", "room1to2", "--after", "2", "--episodes", "3"]
    reference, crashed = tmp_path / "reference", tmp_path / "crashed"
    assert transfer(sources["drago"], *args, "--out", str(reference)) == 0

    # 10 updates per iteration; resume.pt was written after iterations 1 and 2.
    with crash_at_gradient_step(Drago, 25), pytest.raises(SimulatedCrash):
        transfer(sources["drago"], *args, "--out", str(crashed))
    assert load_checkpoint(crashed / "checkpoints" / "resume.pt", kind="resume")["episodes"] == 2
    assert not (crashed / "checkpoints" / "task1_room1to2.pt").exists()

    assert cli.main(["resume", str(crashed), "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv"):
        assert (crashed / name).read_bytes() == (reference / name).read_bytes(), name
    ours = json.loads((crashed / "summary.json").read_text())["transfer"]
    theirs = json.loads((reference / "summary.json").read_text())["transfer"]
    assert ours["few_shot"] == theirs["few_shot"] and ours["total_env_steps"] == theirs["total_env_steps"] == 600


def test_paper_cases_run_in_turn_skip_finished_ones_and_resume_unfinished_ones(smoke_runs, tmp_path, capsys):
    source = smoke_runs("drago")
    cases = [source / "transfer" / f"{task}-after{k}" for task, k in paper_cases("minigrid")]
    assert [c.name for c in cases] == ["room1to2-after2", "room1to3-after3", "room1to3-after4", "room3to4-after4"]
    args = ["--paper-cases", "--episodes", "2"]

    with crash_at_gradient_step(Drago, 15, task="room1to3"), pytest.raises(SimulatedCrash):
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
                                  "no-config", "episodes-zero", "eval-every-misses-few-shot", "exists",
                                  "missing-after", "paper-and-task"])
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
    elif case == "eval-every-misses-few-shot":
        args[5] = "5"
        args += ["--eval-every", "3"]
        expected = ("--eval-every 3", "5 few-shot episodes")
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


# ---------------------------------------------------------------------------------------------------
# DeepMind Control test tasks of Table 1 (paper §4.4, Table 1): X2Y tasks start after a pre-rollout
# ---------------------------------------------------------------------------------------------------
needs_dmc = pytest.mark.skipif(importlib.util.find_spec("dm_control") is None,
                               reason="dm_control is not installed (pip install -e '.[dmc]')")
CHEETAH = ("cheetah-run", "cheetah-jump", "cheetah-run-backwards")  # the paper's sequence, tiny budgets
TINY_CHEETAH = ["env.domain=cheetah", f"env.tasks=[{','.join(CHEETAH)}]", "env.action_repeat=4",
                "env.episode_length=20", "train.steps_per_task=80", "agent.seed_steps=20", "agent.batch_size=16",
                "train.eval_freq=160", "train.checkpoint_freq=80", "train.updates_per_episode=5",
                "train.heldout_episodes=0"]
PRE_STEPS = 100  # the catalogue's pre_rollout_steps


class EpisodeLog:
    """Wraps run_episodes, which plays every episode: how each learner and evaluation episode started (the
    reviewer's, which start from a plain reset, are counted apart in ``reviewer``)."""

    def __init__(self, monkeypatch):
        from drago.continual import drago as drago_module
        from drago.envs import episodes as episodes_module
        from drago.training import trainer as trainer_module

        self.records: list[dict] = []
        self.reviewer, self.playing_reviewer = 0, False
        original, original_one = episodes_module.run_episodes, drago_module.run_episode

        def run(envs, length, choose_actions, start=None):
            episodes = original(envs, length, choose_actions, start)
            for env, episode in zip(envs, episodes if not self.playing_reviewer else []):
                self.records.append({"env": env, "pre_rollout": start is not None, "first": episode.obs[0].copy(),
                                     "elapsed": env.elapsed_steps, "observations": len(episode.obs)})
            return episodes

        def reviewer_episode(env, length, choose_action, start=None):
            self.reviewer += 1
            self.playing_reviewer = True
            try:
                return original_one(env, length, choose_action, start)
            finally:
                self.playing_reviewer = False

        monkeypatch.setattr(episodes_module, "run_episodes", run)  # learner episodes, through run_episode
        monkeypatch.setattr(trainer_module, "run_episodes", run)  # evaluations
        monkeypatch.setattr(drago_module, "run_episode", reviewer_episode)


def manual_pre_rollout(env, ckpt: dict, steps: int = PRE_STEPS):
    """Reset, then the checkpoint's learner in eval mode, written out from the paper (§4.4, Table 1): (plain reset, result)."""
    from drago.agent.agent import Agent
    from drago.envs import env_spec
    from drago.agent.networks import build_world_model

    obs, _ = env.reset()
    plain = obs.copy()
    cfg = Config.from_dict(ckpt["config"])
    world_model = build_world_model(cfg, env_spec("cheetah"), torch.device("cpu"))
    world_model.load_state_dict(ckpt["world_model"])
    agent = Agent(world_model, None, cfg.agent, discrete=False)
    agent.heads.load_state_dict(ckpt["learner"])
    agent.std_floor = ckpt["learner_std_floor"]  # as the learner planned at the end of its task
    seed = int(env.np_random.integers(2**63))
    saved = torch.get_rng_state()
    torch.manual_seed(seed)
    for t in range(steps):
        obs = env.step(agent.act(obs, ckpt["steps"], eval_mode=True, first_step=t == 0))[0]
    torch.set_rng_state(saved)
    return plain, obs


@pytest.fixture(scope="module")
def cheetah_source(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cheetah") / "drago"
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(out), *QUIET, *TINY_CHEETAH]) == 0
    return out


@pytest.fixture(scope="module")
def jump2run(cheetah_source) -> dict:
    """jump2run after stage 2, three learner episodes (DRAGO's reviewer on), every episode start logged."""
    from drago.training.pre_rollout import PreRollout

    calls = {"n": 0}
    original = PreRollout.__call__

    def counted(self, env, task_step=0):
        calls["n"] += 1
        return original(self, env, task_step)

    with pytest.MonkeyPatch.context() as m:
        log = EpisodeLog(m)
        m.setattr(PreRollout, "__call__", counted)
        assert transfer(cheetah_source, "--task", "jump2run", "--after", "2", "--episodes", "3") == 0
    return {"dir": cheetah_source / "transfer" / "jump2run-after2", "records": log.records,
            "pre_rollouts": calls["n"]}


@needs_dmc
def test_x2y_transfer_config_names_its_pre_rollout_learner(jump2run, cheetah_source):
    out = jump2run["dir"]
    cfg = Config.from_dict(yaml.safe_load((out / "config.yaml").read_text()))
    assert cfg.env.tasks == ("cheetah-run",) and cfg.transfer.case == "jump2run" and cfg.transfer.after == 2
    jump = (cheetah_source / "checkpoints" / "task2_cheetah-jump.pt").resolve()
    assert (out / cfg.transfer.checkpoint).resolve() == jump == (out / cfg.transfer.pre_rollout_checkpoint).resolve()
    assert (cfg.transfer.pre_rollout_steps, cfg.transfer.pre_rollout_planning) == (PRE_STEPS, "source")
    assert cfg.train.heldout_episodes == 0 and not (out / "heldout").exists()
    t = json.loads((out / "summary.json").read_text())["transfer"]
    assert t["case"] == "jump2run" and t["pre_rollout"]["steps"] == PRE_STEPS


@needs_dmc
def test_x2y_episodes_start_after_a_pre_rollout_that_is_not_counted(jump2run, cheetah_source):
    records = jump2run["records"]
    # An evaluation (one episode in the smoke preset) before training and after each of 3 learner episodes.
    assert len(records) == 7
    train_env = records[1]["env"]
    kinds = ["train" if r["env"] is train_env else "eval" for r in records]
    assert kinds == ["eval", "train", "eval", "train", "eval", "train", "eval"]
    for r in records:
        # The env ran the pre-rollout and then the episode; the episode holds only its own 20 steps.
        assert r["pre_rollout"] and r["elapsed"] == PRE_STEPS + 20 and r["observations"] == 21
    # Learner and evaluation episodes pre-roll; DRAGO's reviewer episodes start from a plain reset.
    assert jump2run["pre_rollouts"] == 7
    rows = read_csv(jump2run["dir"] / "train.csv")
    assert [int(r["learner_step"]) for r in rows] == [20, 40, 60]  # pre-rollout steps are not counted
    assert [int(r["step"]) for r in rows] == [40, 80, 120]  # learner + reviewer
    t = json.loads((jump2run["dir"] / "summary.json").read_text())["transfer"]
    assert t["learner_env_steps"] == 3 * 20 * 4 and t["total_env_steps"] == 2 * 3 * 20 * 4

    # The first observations are what a pre-rollout written out by hand gives with the same seeds.
    from drago.envs import make_env
    from drago.seeding import task_seed

    ckpt = load_checkpoint(cheetah_source / "checkpoints" / "task2_cheetah-jump.pt", kind="task")
    env = make_env("cheetah", "cheetah-run", action_repeat=4)
    env.reset(seed=task_seed(1, 0, 2))  # the transfer task's training env
    plain, pre = manual_pre_rollout(env, ckpt)
    assert not np.allclose(records[1]["first"], plain)
    np.testing.assert_array_equal(records[1]["first"], pre)
    env = make_env("cheetah", "cheetah-run", action_repeat=4)
    env.reset(seed=task_seed(1, 0, 3, 0, 0))  # the first evaluation env at env step 0
    plain, pre = manual_pre_rollout(env, ckpt)
    assert not np.allclose(records[0]["first"], plain)
    np.testing.assert_array_equal(records[0]["first"], pre)


@needs_dmc
def test_reset_test_tasks_have_no_pre_rollout(cheetah_source, tmp_path, monkeypatch):
    log = EpisodeLog(monkeypatch)
    out = tmp_path / "jump-and-run"
    assert transfer(cheetah_source, "--task", "jump-and-run", "--after", "2", "--episodes", "1", "--out", str(out)) == 0
    cfg = Config.from_dict(yaml.safe_load((out / "config.yaml").read_text()))
    assert cfg.env.tasks == ("cheetah-jump-and-run",) and cfg.transfer.case == "jump-and-run"
    assert cfg.transfer.pre_rollout_checkpoint is None
    assert [(r["pre_rollout"], r["elapsed"]) for r in log.records] == [(False, 20)] * 3
    from drago.envs import make_env
    from drago.seeding import task_seed

    env = make_env("cheetah", "cheetah-jump-and-run", action_repeat=4)
    env.reset(seed=task_seed(1, 0, 2))
    np.testing.assert_array_equal(log.records[1]["first"], env.reset()[0])


@needs_dmc
def test_x2y_transfer_is_deterministic_and_resumes_after_a_crash(jump2run, cheetah_source, tmp_path):
    args = ["--task", "jump2run", "--after", "2", "--episodes", "3"]
    again, crashed = tmp_path / "again", tmp_path / "crashed"
    assert transfer(cheetah_source, *args, "--out", str(again)) == 0
    for name in ("train.csv", "eval.csv"):
        assert (again / name).read_bytes() == (jump2run["dir"] / name).read_bytes(), name

    # 5 updates per iteration; resume.pt was written after iterations 1 and 2.
    with crash_at_gradient_step(Drago, 12), pytest.raises(SimulatedCrash):
        transfer(cheetah_source, *args, "--out", str(crashed))
    assert load_checkpoint(crashed / "checkpoints" / "resume.pt", kind="resume")["episodes"] == 2
    assert cli.main(["resume", str(crashed), "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv"):
        assert (crashed / name).read_bytes() == (jump2run["dir"] / name).read_bytes(), name


@needs_dmc
def test_dmc_paper_cases_follow_table_1(cheetah_source, tmp_path):
    out = tmp_path / "cases"
    assert paper_cases("cheetah") == (("jump2run", 2), ("jump2back", 3), ("jump-and-run", 2), ("jump-and-back", 3))
    assert transfer(cheetah_source, "--paper-cases", "--episodes", "1", "--out", str(out)) == 0
    ckpts = cheetah_source / "checkpoints"
    expected = {  # case: (target, world model after, pre-rollout learner)
        "jump2run-after2": ("cheetah-run", "task2_cheetah-jump.pt", "task2_cheetah-jump.pt"),
        "jump2back-after3": ("cheetah-run-backwards", "task3_cheetah-run-backwards.pt", "task2_cheetah-jump.pt"),
        "jump-and-run-after2": ("cheetah-jump-and-run", "task2_cheetah-jump.pt", None),
        "jump-and-back-after3": ("cheetah-jump-and-run-backwards", "task3_cheetah-run-backwards.pt", None),
    }
    assert sorted(p.name for p in out.iterdir()) == sorted(expected)
    for case, (target, world, pre) in expected.items():
        cfg = Config.from_dict(yaml.safe_load((out / case / "config.yaml").read_text()))
        assert cfg.env.tasks == (target,) and cfg.transfer.case == case.rsplit("-after", 1)[0]
        assert (out / case / cfg.transfer.checkpoint).resolve() == (ckpts / world).resolve()
        if pre is None:
            assert cfg.transfer.pre_rollout_checkpoint is None
        else:
            assert (out / case / cfg.transfer.pre_rollout_checkpoint).resolve() == (ckpts / pre).resolve()
        assert json.loads((out / case / "summary.json").read_text())["complete"] is True


@needs_dmc
@pytest.mark.parametrize("planning", ["source", "code"])
def test_pre_rollout_planning(cheetah_source, planning, monkeypatch):
    """source: the learner's own end-of-task horizon and std floor; code: the official quirk (paper §4.4, Table 1)."""
    from drago.envs import make_env
    from drago.training.pre_rollout import PreRollout, load_learner

    path = cheetah_source / "checkpoints" / "task2_cheetah-jump.pt"
    ckpt = load_checkpoint(path, kind="task")
    pre = PreRollout(load_learner(path), steps=3, planning=planning)
    seen = []

    def act(obs, step, eval_mode, first_step, bonus=None):
        seen.append((step, eval_mode, first_step, pre.learner.agent.std_floor))
        return np.zeros(6, dtype=np.float32)

    monkeypatch.setattr(pre.learner.agent, "act", act)
    env = make_env("cheetah", "cheetah-run", action_repeat=4)
    env.reset(seed=0)
    pre(env, task_step=7)
    step, floor = (ckpt["steps"], ckpt["learner_std_floor"]) if planning == "source" else (7, 0.5)
    assert seen == [(step, True, True, floor), (step, True, False, floor), (step, True, False, floor)]
    assert env.elapsed_steps == 3


@needs_dmc
@pytest.mark.parametrize("case", ["unknown", "other-domain", "source-stage-missing", "paper-cases-partial"])
def test_dmc_transfer_errors_are_one_line(cheetah_source, tmp_path, capsys, case):
    source = cheetah_source
    args = ["--task", "jump2run", "--after", "1", "--out", str(tmp_path / "t")]
    if case == "unknown":
        args[1] = "jump2walk"
        expected = ("jump2walk", "test tasks: jump2run, jump2back", "cheetah-jump-and-run")
    elif case == "other-domain":
        args[1] = "walk2run"
        expected = ("unknown task 'walk2run' for domain cheetah",)
    else:
        partial = tmp_path / "partial"
        (partial / "checkpoints").mkdir(parents=True)
        (partial / "config.yaml").write_bytes((source / "config.yaml").read_bytes())
        (partial / "checkpoints" / "task1_cheetah-run.pt").write_bytes(
            (source / "checkpoints" / "task1_cheetah-run.pt").read_bytes())
        source = partial
        if case == "source-stage-missing":
            expected = ("task2_cheetah-jump.pt", "cheetah-jump learner", "finished stages: 1")
        else:
            args = ["--paper-cases"]
            expected = ("stage 2", "finished stages: 1")
    capsys.readouterr()
    assert transfer(source, *args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drago: error: ") and len(err.splitlines()) == 1 and "Traceback" not in err, err
    for text in expected:
        assert text in err, (text, err)
