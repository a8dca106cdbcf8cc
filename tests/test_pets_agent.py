"""PETS wired into drago (docs: Methods, PETS): agent.kind=pets through the trainer, the continual methods,
checkpoints and resume, transfers and the evaluations that read a run's world model.

The core (ensemble, trajectory sampling, CEM) is tested on its own in tests/test_pets.py; here the runs are
tiny: the smoke preset with a two-member ensemble and a planner of a few dozen sequences.
"""

from __future__ import annotations

import copy
import importlib.util
import json
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers import ONE_THREAD_ENV, QUIET, read_csv, sigkill_in_task_two

from drago import cli
from drago.agent import pets as pets_module
from drago.agent.factory import build_agent, build_world_model, build_world_optimizer
from drago.agent.pets import (
    PetsAgent,
    PetsWorldModel,
    ProbabilisticEnsemble,
    RewardHead,
    gaussian_nll,
)
from drago.config import ConfigError, load_config
from drago.continual import check_method
from drago.continual.generative import intrinsic_reward, rehearsal_loss
from drago.envs import env_spec
from drago.training.checkpoint import load_checkpoint

DRAGO = Path(sys.executable).parent / "drago"
#: A PETS agent small enough for seconds-long runs.
PETS = ["agent.kind=pets", "agent.pets.members=2", "agent.pets.hidden=16", "agent.pets.layers=2",
        "agent.pets.particles=2", "agent.pets.horizon=3", "agent.pets.iterations=2", "agent.pets.population=12",
        "agent.pets.elites=3", "agent.batch_size=16"]
#: Two tasks of four 20-step episodes, the first two random, evaluated at each task's start and end; dense
#: transfers, as the PETS presets ask.
TWO_TASKS = ["env.tasks=[room1,room2]", "env.episode_length=20", "train.steps_per_task=80", "agent.seed_steps=40",
             "train.eval_freq=80", "train.checkpoint_freq=40", "transfer.reward=dense"]
needs_dmc = pytest.mark.skipif(importlib.util.find_spec("dm_control") is None,
                               reason="dm_control is not installed (pip install -e '.[dmc]')")
METHODS = ("scratch", "continual", "drago", "drago-no-reviewer", "drago-no-rehearsal", "replay", "ewc")


def train(out: Path, method: str, *extra: str) -> int:
    return cli.main(["train", "smoke", "--method", method, "--out", str(out), *QUIET, *PETS, *TWO_TASKS, *extra])


@pytest.fixture(scope="module")
def pets_runs(tmp_path_factory):
    """``pets_runs(method)``: a finished two-task PETS grid run of that method, trained once per module."""
    done: dict[str, Path] = {}
    root = tmp_path_factory.mktemp("pets-runs")

    def get(method: str) -> Path:
        if method not in done:
            out = root / method
            assert train(out, method, *(["method.ewc.fisher_batches=2"] if method == "ewc" else [])) == 0
            done[method] = out
        return done[method]

    return get


# ---------------------------------------------------------------------------------------------------
# Every method through the same interface
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_each_method_trains_a_pets_grid_run(pets_runs, method):
    run = pets_runs(method)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["complete"] and [t["name"] for t in summary["tasks"]] == ["room1", "room2"]
    rows = read_csv(run / "train.csv")
    task2 = [r for r in rows if r["task"] == "room2"]
    last = task2[-1]
    world = "reviewer" if method in ("drago", "drago-no-rehearsal") else "learner"
    assert np.isfinite(float(last[f"{world}_model_nll"]))  # the ensemble is trained, by the reviewer in DRAGO
    assert np.isfinite(float(last["learner_reward_loss"]))  # the learner's own reward head
    if method in ("drago", "drago-no-rehearsal"):
        assert float(last["reviewer_reward_loss"]) >= 0 and "reviewer_episode_reward" in last
        assert int(last["step"]) == 2 * int(last["learner_step"])  # reviewer episodes share the budget
    if method in ("drago", "drago-no-reviewer"):
        assert float(last["rehearsal_loss"]) >= 0
    if method == "replay":
        assert float(last["learner_model_extra_loss"]) != 0  # old transitions' NLL in the ensemble's objective
    if method == "ewc":
        assert float(last["learner_model_extra_loss"]) >= 0
    # The task checkpoint holds the ensemble and the learner's reward head, and the next task starts from it.
    first = load_checkpoint(run / "checkpoints" / "task1_room1.pt", kind="task")
    assert any(k.startswith("ensemble.") for k in first["world_model"])
    assert "net.0.weight" in first["learner"]


@pytest.mark.slow
def test_scratch_starts_each_task_afresh_and_continual_carries_the_ensemble(pets_runs):
    for method, carried in (("continual", True), ("scratch", False)):
        run = pets_runs(method)
        task1 = load_checkpoint(run / "checkpoints" / "task1_room1.pt")["world_model"]
        task2 = load_checkpoint(run / "checkpoints" / "task2_room2.pt")["world_model"]
        # The input statistics pool every row the ensemble was trained on: carried, they count task 1's too.
        assert bool(task2["ensemble.input_count"] > task1["ensemble.input_count"]) is carried


# ---------------------------------------------------------------------------------------------------
# What a PETS run's evaluations read: the ensemble's mean prediction
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_coverage_zero_shot_and_the_predictor_read_the_ensemble_mean(pets_runs):
    from drago.eval.coverage import coverage_of_run
    from drago.eval.predictor import load_world_model
    from drago.eval.zero_shot import zero_shot_matrix

    run = pets_runs("drago")
    predictor = load_world_model(run / "checkpoints" / "task2_room2.pt")
    assert isinstance(predictor.world_model, PetsWorldModel)
    obs = np.array([[0.0, 0.0, -1.0], [0.5, -0.5, 0.0]], dtype=np.float32)
    action = np.eye(3, dtype=np.float32)[[2, 0]]
    ensemble = predictor.world_model.ensemble
    with torch.no_grad():
        mean, _ = ensemble(torch.from_numpy(obs), torch.from_numpy(action))
    expected = (torch.from_numpy(obs) + mean.mean(0)).clamp(-1, 1).numpy()
    np.testing.assert_allclose(predictor.predict(obs, action), expected, rtol=1e-6, atol=1e-6)

    rows = coverage_of_run(run)
    assert [r["stage"] for r in rows if r["room"] == "all"] == [1, 2]
    assert all(0.0 <= r["accuracy"] <= 1.0 and np.isfinite(r["score"]) for r in rows)
    zero = zero_shot_matrix(run, tasks=["room1"], episodes=1, horizon=5)
    assert [r["stage"] for r in zero] == [1, 2] and all(np.isfinite(r["return"]) for r in zero)


@pytest.mark.slow
def test_the_four_grid_transfer_cases_run_from_a_pets_run_with_dense_reward(pets_runs, tmp_path, capsys):
    from drago.study.plan import plan_study
    from drago.envs import get_domain
    from drago.training.transfer import transfer_config

    run = pets_runs("drago")
    out = tmp_path / "room1to2"
    assert cli.main(["transfer", str(run), "--task", "room1to2", "--after", "2", "--episodes", "1", "--out", str(out),
                     "--no-progress"]) == 0
    block = json.loads((out / "summary.json").read_text())["transfer"]
    assert block["reward"] == "dense" and block["optimal_return"] > 200  # the DP optimum about 266; sparse: 1
    assert load_checkpoint(out / "checkpoints" / "task1_room1to2.pt")["config"]["agent"]["kind"] == "pets"
    # On the four-task preset every case of the paper is planned, each a dense PETS transfer.
    source = load_config("minigrid-pets-cpu", method="drago")
    for task, after in get_domain("minigrid").transfer_cases:
        cfg = transfer_config(source, task, "task.pt", after)
        assert cfg.env.dense_reward is True and cfg.agent.kind == "pets"
    plan = plan_study("minigrid-pets-cpu", methods=["drago", "continual", "scratch"], seeds=[1],
                      out=tmp_path / "study", transfers=True)
    assert [(j.method, j.kind) for j in plan.runs] == [("drago", "run"), ("continual", "run"), ("scratch", "run")]
    assert sorted({j.label.split(" ", 2)[-1] for j in plan.transfers}) == [
        "room1to2-after2", "room1to3-after3", "room1to3-after4", "room3to4-after4"]


# ---------------------------------------------------------------------------------------------------
# Rehearsal and the intrinsic reward against an ensemble, on hand-made rows
# ---------------------------------------------------------------------------------------------------
def _ensemble_world_model(seed: int) -> PetsWorldModel:
    torch.manual_seed(seed)
    return PetsWorldModel(ProbabilisticEnsemble(3, 3, members=3, hidden=8, layers=2, predict_reward=False), (-1.0, 1.0))


def test_rehearsal_pulls_each_member_towards_its_frozen_old_self():
    old = _ensemble_world_model(0).requires_grad_(False)
    current = copy.deepcopy(old).requires_grad_(True)
    states = torch.tensor([[0.1, -0.2, 0.5], [0.9, 0.9, -1.0], [-0.4, 0.3, 0.0], [0.0, 0.0, 1.0]])
    actions = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.2, 0.7, 0.1], [0.0, 1.0, 0.0]])  # VAE rows are raw
    assert rehearsal_loss(current, old, states, actions).item() == 0.0  # a copy has nothing to rehearse
    with torch.no_grad():
        current.ensemble.head.bias[1].add_(0.3)  # member 1 drifts; the others stay
    mean_old, _ = old.ensemble(states, actions)
    mean_cur, _ = current.ensemble(states, actions)
    by_hand = (mean_cur[..., :3] - mean_old[..., :3]).pow(2).mean()  # member by member, every output of the state
    loss = rehearsal_loss(current, old, states, actions, "pre_squash")
    assert loss.item() == pytest.approx(by_hand.item(), rel=1e-6) and loss.item() > 0
    post = rehearsal_loss(current, old, states, actions, "post_squash")
    expected = (current(states, actions) - old(states, actions)).pow(2).mean()  # the clamped ensemble means
    assert post.item() == pytest.approx(expected.item(), rel=1e-6)
    # One step of rehearsal brings the drifted member back; the frozen model does not move.
    optimizer = torch.optim.SGD(current.parameters(), lr=0.5)
    before = [p.clone() for p in old.parameters()]
    loss.backward()
    optimizer.step()
    assert rehearsal_loss(current, old, states, actions).item() < loss.item()
    assert all(torch.equal(a, b) for a, b in zip(before, old.parameters()))


def test_intrinsic_reward_compares_old_and_current_ensemble_errors():
    old, current = _ensemble_world_model(0), _ensemble_world_model(1)
    obs = torch.tensor([[0.1, -0.2, 0.5], [0.3, 0.3, -1.0]])
    actions = torch.eye(3)[[2, 0]]
    next_obs = old(obs, actions)  # what the old model predicts exactly
    r = intrinsic_reward(old, current, obs, actions, next_obs, threshold=5.0, cost_coef=0.5)
    cur_err = (current(obs, actions) - next_obs).pow(2).mean(-1)
    assert torch.allclose(r.old_reward, torch.sigmoid(4.0 * (-torch.log(torch.tensor(1e-10)) - 5.0)))
    assert torch.allclose(r.cost, torch.sigmoid(-torch.log(cur_err + 1e-10) - 5.0))
    assert torch.allclose(r.reward, r.old_reward - 0.5 * r.cost)
    # Any leading shape, as DRAGO relabels (H+1, B) sequences.
    seq = intrinsic_reward(old, current, obs[None].expand(4, -1, -1), actions[None].expand(4, -1, -1),
                           next_obs[None].expand(4, -1, -1), 5.0, 0.5)
    assert seq.reward.shape == (4, 2) and torch.allclose(seq.reward[3], r.reward)


def test_transition_loss_is_the_ensembles_nll_of_the_state_deltas():
    model = _ensemble_world_model(0)
    obs, actions = torch.rand(5, 3) * 2 - 1, torch.eye(3)[[0, 1, 2, 2, 1]]
    next_obs = torch.rand(5, 3) * 2 - 1
    mean, logvar = model.ensemble(obs, actions)
    expected = gaussian_nll(mean, logvar, (next_obs - obs).expand(3, -1, -1)).sum()
    assert model.transition_loss(obs, actions, next_obs).item() == pytest.approx(expected.item(), rel=1e-6)


# ---------------------------------------------------------------------------------------------------
# The agent behind the trainer's surface
# ---------------------------------------------------------------------------------------------------
def test_the_learner_learns_its_own_reward_and_keeps_a_uniform_priority():
    cfg = load_config("smoke", PETS)
    spec = env_spec("minigrid")
    world_model = build_world_model(cfg, spec)
    agent = build_agent(cfg, spec, world_model, build_world_optimizer(cfg, world_model), task="room1")
    assert isinstance(agent, PetsAgent) and isinstance(agent.reward_head, RewardHead)
    rows = 6
    batch = SimpleNamespace(obs=torch.rand(rows, 3), next_obs=torch.rand(2, rows, 3), actions=torch.eye(3)[[0] * rows][None].repeat(2, 1, 1),
                            rewards=torch.ones(2, rows))
    losses = [float(agent.update(batch, 0)["reward_loss"]) for _ in range(30)]
    assert losses[-1] < losses[0]
    out = agent.update(batch, 0, train_world_model=False, policy_rows=4)
    assert set(out) == {"reward_loss", "priority"} and torch.equal(out["priority"], torch.ones(4))
    assert "mean_prediction_score" in agent.update(batch, 0)
    state = agent.state_dict()
    other = build_agent(cfg, spec, world_model, None, task="room1")
    other.load_state_dict(state)
    probe = (torch.rand(4, 3), torch.eye(3)[[0, 1, 2, 0]], torch.rand(4, 3))
    assert torch.equal(other.reward_head(*probe), agent.reward_head(*probe))
    # The known reward: the learner plans on the grid's own reward and learns none.
    known = build_agent(load_config("smoke", [*PETS, "agent.pets.reward=known"]), spec, world_model, None, task="room1")
    assert known.reward_head is None and set(known.update(batch, 0, train_world_model=False)) == {"priority"}
    action = known.act(np.zeros(3, dtype=np.float32), 0, eval_mode=True, first_step=True)
    assert action.sum() == 1


@needs_dmc
def test_a_continuous_plan_warm_starts_the_next_one(monkeypatch):
    cfg = load_config("smoke", [*PETS, "env.domain=cheetah", "env.tasks=[cheetah-run]", "env.action_repeat=4"])
    spec = env_spec("cheetah")
    world_model = build_world_model(cfg, spec)
    agent = build_agent(cfg, spec, world_model, None, task="cheetah-run")
    seen = []
    original = pets_module.cem

    def recording(*args, **kwargs):
        seen.append(kwargs.get("warm_mean"))
        return original(*args, **kwargs)

    monkeypatch.setattr(pets_module, "cem", recording)
    obs = np.zeros(spec.obs_dim, dtype=np.float32)
    agent.act(obs, 0, eval_mode=False, first_step=True)
    agent.act(obs, 0, eval_mode=False, first_step=False)
    agent.act(np.zeros((2, spec.obs_dim), dtype=np.float32), 0, eval_mode=True, first_step=False)  # another batch
    assert seen[0] is None and seen[1] is not None and seen[1].shape == (3, spec.action_dim) and seen[2] is None


# ---------------------------------------------------------------------------------------------------
# Settings: what PETS cannot do is said in one line, before anything runs
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method, extra, words", [
    ("curiosity", [], ["method 'curiosity'", "needs a learned value", "agent.kind=pets"]),
    ("drago-single-agent", ["agent.pets.reward=known"], ["method 'drago-single-agent'", "agent.pets.reward=learned"]),
])
def test_a_method_pets_cannot_serve_says_so_in_one_line(method, extra, words, tmp_path, capsys):
    with pytest.raises(ConfigError) as err:
        check_method(load_config("smoke", [*PETS, *extra], method=method))
    assert all(w in str(err.value) for w in words) and "\n" not in str(err.value)
    assert cli.main(["train", "smoke", "--method", method, "--out", str(tmp_path / "run"), *QUIET, *PETS, *extra]) == 2
    message = capsys.readouterr().err.strip()
    assert len(message.splitlines()) == 1 and all(w in message for w in words)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("override, words", [
    ("agent.kind=petz", "unknown agent.kind 'petz'; valid choices: tdmpc, pets"),
    ("agent.pets.elites=50", "agent.pets.elites (50) must not exceed agent.pets.population (12)"),
    ("agent.pets.propagation=ts2", "valid choices: tsinf, ts1"),
    ("agent.pets.members=0", "setting 'agent.pets.members' must be positive"),
    ("agent.tdmpc.precision=bfloat16", "setting 'agent.tdmpc.precision' applies to agent.kind=tdmpc, and this run is "
                                        "agent.kind=pets"),
    ("transfer.reward=dens", "unknown transfer.reward 'dens'; valid choices: dense, sparse"),
    ("agent.pets.reward=known env.domain=cheetah env.tasks=[cheetah-run]",
     "agent.pets.reward=known needs a reward known as a function of observations"),
])
def test_pets_settings_are_validated(override, words):
    with pytest.raises(ConfigError, match=words.replace("(", r"\(").replace(")", r"\)")):
        load_config("smoke", [*PETS, *override.split()])


def test_the_pets_presets():
    gpu, cpu = load_config("minigrid-pets"), load_config("minigrid-pets-cpu")
    for cfg in (gpu, cpu):
        assert cfg.agent.kind == "pets" and cfg.transfer.reward == "dense" and cfg.env.domain == "minigrid"
        assert cfg.agent.pets.particles % cfg.agent.pets.members == 0  # every member gets as many particles
        for method in METHODS:
            check_method(load_config(cfg.preset, method=method))
    assert (gpu.agent.pets.population, gpu.agent.pets.elites, gpu.agent.pets.particles) == (400, 40, 20)
    assert cpu.train.steps_per_task < gpu.train.steps_per_task


# ---------------------------------------------------------------------------------------------------
# Crash and resume
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_sigkill_then_resume_gives_the_uninterrupted_logs(tmp_path):
    """SIGKILL of a DRAGO-PETS run inside task 2 after a periodic checkpoint; `drago resume` then writes the
    logs of an uninterrupted run: the reviewer's reward head, its buffer and the ensemble all come back."""
    longer = ["train.steps_per_task=120", "train.checkpoint_freq=20", "train.eval_freq=120"]
    args = ["smoke", "--method", "drago", *QUIET, *PETS, *TWO_TASKS, *longer]
    reference = tmp_path / "reference"
    assert cli.main(["train", *args, "--out", str(reference)]) == 0

    run = tmp_path / "killed"
    code = sigkill_in_task_two(args, run, tmp_path, wait_s=120)
    resume_ckpt = run / "checkpoints" / "resume.pt"
    assert code == -signal.SIGKILL
    assert load_checkpoint(resume_ckpt, kind="resume")["task_index"] == 1
    assert not (run / "checkpoints" / "task2_room2.pt").exists()
    done = subprocess.run([str(DRAGO), "resume", str(run), "--no-progress"], capture_output=True, text=True,
                          env=ONE_THREAD_ENV, cwd=tmp_path, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    for name in ("train.csv", "eval.csv"):
        assert (run / name).read_bytes() == (reference / name).read_bytes(), name


# ---------------------------------------------------------------------------------------------------
# Continuous actions
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
@needs_dmc
def test_a_cheetah_pets_smoke_run(tmp_path):
    from drago.eval.heldout import retention_matrix
    from drago.training.pre_rollout import load_learner

    tiny = ["env.domain=cheetah", "env.tasks=[cheetah-run,cheetah-jump]", "env.action_repeat=4",
            "env.episode_length=20", "train.steps_per_task=80", "agent.seed_steps=20", "train.eval_freq=160",
            "train.checkpoint_freq=80", "train.updates_per_episode=5", "train.heldout_episodes=1"]
    out = tmp_path / "cheetah"
    args = ["train", "smoke", "--method", "drago", "--out", str(out), *QUIET, *PETS, *tiny]
    assert cli.main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and all(np.isfinite(t["final_eval_return"]) for t in summary["tasks"])
    rows = read_csv(out / "train.csv")
    assert any(r["task"] == "cheetah-jump" and r["reviewer_model_nll"] for r in rows)  # the reviewer trained it
    retention = retention_matrix(out)
    assert len(retention) == 4 and all(np.isfinite(r["error"]) for r in retention)
    learner = load_learner(out / "checkpoints" / "task2_cheetah-jump.pt")  # what an X2Y pre-rollout drives
    action = learner.agent.act(np.zeros(env_spec("cheetah").obs_dim, dtype=np.float32), 0, True, True)
    assert action.shape == (env_spec("cheetah").action_dim,) and np.abs(action).max() <= 1.0
