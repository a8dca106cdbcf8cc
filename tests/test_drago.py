"""DRAGO's maths and its method object, against paper §3."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from drago import cli
from drago.agent.networks import WorldModel
from drago.continual.generative import (
    VAE,
    ContinuousCounts,
    GridCounts,
    intrinsic_reward,
    rehearsal_loss,
    vae_loss,
)
from drago.envs.fourrooms import observation, traversable_cells
from drago.training.checkpoint import load_checkpoint
from helpers import tdmpc_config, SimulatedCrash, crash_at_gradient_step


def _world_model(seed: int) -> WorldModel:
    torch.manual_seed(seed)
    return WorldModel(3, 3, 32, use_crelu=False, squash=True)


def _transitions(n: int = 256, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.rand(n, 3, generator=g) * 2 - 1
    actions = torch.nn.functional.one_hot(torch.randint(0, 3, (n,), generator=g), 3).float()
    next_obs = torch.rand(n, 3, generator=g) * 2 - 1
    return obs, actions, next_obs


class _Exact(torch.nn.Module):
    """A stand-in world model that predicts a given next state exactly (or with a chosen error)."""

    def __init__(self, target: torch.Tensor, error: float = 0.0):
        super().__init__()
        self.target, self.error = target, error

    def encode(self, obs):
        return obs

    def forward(self, z, a):
        return self.target + self.error


@pytest.mark.parametrize("variant", ["code", "paper"])
def test_intrinsic_reward_lies_in_its_range(variant):
    obs, actions, next_obs = _transitions()
    for old_seed, cur_seed in [(0, 1), (2, 2), (3, 4)]:
        r = intrinsic_reward(_world_model(old_seed), _world_model(cur_seed), obs, actions, next_obs,
                             threshold=9.5, cost_coef=0.5, variant=variant)
        assert r.reward.shape == (256,)
        assert torch.all(r.reward > -0.5) and torch.all(r.reward < 1.0)
        assert torch.allclose(r.reward, r.old_reward - 0.5 * r.cost)


def test_intrinsic_reward_rises_where_old_model_is_right_and_current_is_wrong():
    obs, actions, next_obs = _transitions(64)
    right, wrong = _Exact(next_obs), _Exact(next_obs, error=0.5)
    theta = 9.5
    best = intrinsic_reward(right, wrong, obs, actions, next_obs, theta, 0.5).reward
    worst = intrinsic_reward(wrong, right, obs, actions, next_obs, theta, 0.5).reward
    both_right = intrinsic_reward(right, right, obs, actions, next_obs, theta, 0.5).reward
    both_wrong = intrinsic_reward(wrong, wrong, obs, actions, next_obs, theta, 0.5).reward
    assert torch.all(best > both_right) and torch.all(best > both_wrong) and torch.all(both_wrong > worst)
    # Closed forms of the code variant: an exact old model scores -log(1e-10) = 23.03 >> theta -> r_old ~ 1;
    # an error of 0.5 in every dim scores -log(0.25) = 1.386 -> cost sigmoid(1.386 - 9.5) ~ 3e-4.
    assert torch.allclose(best, torch.full_like(best, 1 - 0.5 * 1 / (1 + math.exp(9.5 - math.log(4)))), atol=1e-4)
    assert torch.allclose(worst, torch.full_like(worst, 1 / (1 + math.exp(-4 * (math.log(4) - 9.5))) - 0.5), atol=1e-4)


def test_intrinsic_reward_threshold_is_the_midpoint_of_the_old_term():
    obs, actions, next_obs = _transitions(8)
    mse = math.exp(-9.5)  # a prediction score exactly at theta
    old = _Exact(next_obs, error=math.sqrt(mse))
    r = intrinsic_reward(old, old, obs, actions, next_obs, threshold=9.5, cost_coef=0.0)
    assert torch.allclose(r.old_reward, torch.full((8,), 0.5), atol=1e-3)


def test_vae_loss_closed_form():
    x = torch.tensor([[1.0, 0.0], [0.0, 2.0]])
    recon = torch.zeros(2, 2)
    mu = torch.tensor([[1.0, 0.0], [0.0, 0.0]])
    log_var = torch.zeros(2, 2)
    total, rec, kl = vae_loss(recon, x, mu, log_var, recon_coef=1.0, kl_coef=0.5)
    assert rec.item() == pytest.approx((1 + 4) / 4)
    # KL per element = -0.5 (1 + 0 - mu^2 - 1) = mu^2 / 2, averaged over batch AND latent dims.
    assert kl.item() == pytest.approx(0.5 / 4)
    assert total.item() == pytest.approx(rec.item() + 0.5 * kl.item())


def test_rehearsal_pulls_a_perturbed_model_back_to_the_frozen_one_on_generated_inputs():
    torch.manual_seed(0)
    old = _world_model(0).requires_grad_(False)
    current = copy.deepcopy(old).requires_grad_(True)
    with torch.no_grad():
        for p in current.dynamics.parameters():
            p.add_(0.3 * torch.randn_like(p))
    # A generator of (state, action) pairs: a VAE fitted for a few steps on grid data stands in for G_old.
    vae = VAE(6, 32, 8)
    cells = traversable_cells()
    data = torch.tensor(np.array([np.concatenate([observation(c, d), np.eye(3)[a]])
                                  for c in cells[::7] for d in range(4) for a in range(3)]), dtype=torch.float32)
    opt = torch.optim.Adam(vae.parameters(), lr=1e-3)
    for _ in range(200):
        rec, mu, lv = vae(data)
        loss = vae_loss(rec, data, mu, lv, 1.0, 0.02)[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
    probe = vae.sample(512)
    states, actions = probe[:, :3], probe[:, 3:]

    def gap(target):
        return rehearsal_loss(current, old, states, actions, target).item()

    before_pre, before_post = gap("pre_squash"), gap("post_squash")
    optimizer = torch.optim.Adam(current.dynamics.parameters(), lr=1e-3)
    for _ in range(300):
        sample = vae.sample(512)
        loss = rehearsal_loss(current, old, sample[:, :3], sample[:, 3:], "pre_squash")
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert gap("pre_squash") < 0.1 * before_pre
    assert gap("post_squash") < 0.1 * before_post
    assert all(not p.requires_grad for p in old.parameters())


def test_rehearsal_loss_is_zero_between_identical_models():
    wm = _world_model(0)
    obs, actions, _ = _transitions(16)
    assert rehearsal_loss(wm, copy.deepcopy(wm), obs, actions).item() == 0.0


def test_grid_counts_round_exact_observations_to_their_own_cell():
    counts = GridCounts()
    cells = [(x, y) for x in range(1, 26) for y in range(1, 26)]
    obs = torch.tensor(np.array([observation(c, d) for c in cells for d in range(4)]))
    x, y, d = counts.index(obs)
    expected = torch.tensor([(c[0], c[1], h) for c in cells for h in range(4)])
    assert torch.equal(torch.stack((x, y, d), 1), expected)
    # The official code's truncation would misfile x in {2, 3, 6, 9}: rounding does not.
    counts.update(torch.tensor(observation((2, 3), 1)))
    counts.update(torch.tensor(observation((2, 3), 1)))
    assert counts.table[2, 3, 1] == 2 and counts.table.sum() == 2


def test_grid_count_bonus_closed_form():
    counts = GridCounts()
    o = torch.tensor(observation((5, 5), 0))
    assert counts.bonus(o).item() == pytest.approx(1 / math.sqrt(0.99999) - 1 / 99999)
    for _ in range(3):
        counts.update(o)
    assert counts.bonus(o).item() == pytest.approx(1 / math.sqrt(3.99999) - 1 / 99999)


@pytest.fixture(scope="module")
def drago_run(smoke_runs):
    return smoke_runs("drago")


@pytest.mark.slow
def test_task_checkpoint_carries_world_model_vae_and_threshold_only(drago_run):
    ckpt = load_checkpoint(drago_run / "checkpoints" / "task2_room2.pt", kind="task")
    assert set(ckpt["method"]) == {"vae", "threshold", "tasks_seen"}
    assert isinstance(ckpt["method"]["threshold"], float) and math.isfinite(ckpt["method"]["threshold"])
    # No reviewer, optimizer or buffer crosses a task boundary (paper §3.3; docs: Design, how a run flows).
    assert not any(k.startswith(("reviewer", "optimizer", "buffer")) for k in ckpt)


@pytest.mark.slow
def test_next_task_starts_from_the_saved_world_model_vae_and_threshold(drago_run, monkeypatch):
    from drago.continual.drago import Drago
    from drago.config import Config
    import yaml

    cfg = Config.from_dict(yaml.safe_load((drago_run / "config.yaml").read_text()))
    ckpt = load_checkpoint(drago_run / "checkpoints" / "task2_room2.pt", kind="task")
    method = Drago(cfg, __import__("drago.envs", fromlist=["env_spec"]).env_spec("minigrid"), torch.device("cpu"))
    method.load_carry_state(ckpt["method"])
    assert method.threshold == ckpt["method"]["threshold"]
    for key, value in ckpt["method"]["vae"].items():
        assert torch.equal(method.vae.state_dict()[key], value)


@pytest.mark.slow
def test_drago_logs_reviewer_and_rehearsal_in_later_tasks(drago_run):
    import csv

    rows = list(csv.DictReader((drago_run / "train.csv").open()))
    first = [r for r in rows if r["task"] == "room1"]
    later = [r for r in rows if r["task"] != "room1" and r["reviewer_consistency_loss"]]
    assert first and later
    assert all(r["reviewer_episode_reward"] == "" for r in first)
    for r in later:
        assert float(r["learner_consistency_loss"]) == 0.0  # only the reviewer trains the world model
        assert float(r["rehearsal_loss"]) >= 0.0
        # reviewer episodes count against the task budget (the official code's accounting)
        assert int(r["step"]) == 2 * int(r["learner_step"])


@pytest.mark.slow
def test_drago_resume_replays_exactly(tmp_path):
    from drago.continual import drago as drago_module

    reference = tmp_path / "ref"
    # Two rooms: the crash comes in the second, where every piece of DRAGO's state is live.
    args = ["train", "smoke", "--method", "drago", "--no-progress", "train.tensorboard=false",
            "env.tasks=[room1,room2]", "train.steps_per_task=600", "train.checkpoint_freq=200"]
    assert cli.main([*args, "--out", str(reference)]) == 0

    crashed = tmp_path / "crashed"
    # the last iteration of task 2 (updates 11-20), after its checkpoint at step 400
    with crash_at_gradient_step(drago_module.Drago, 15, task=1), pytest.raises(SimulatedCrash):
        cli.main([*args, "--out", str(crashed)])
    snapshot = load_checkpoint(crashed / "checkpoints" / "resume.pt", kind="resume")
    assert snapshot["task_index"] == 1  # resumed inside task 2, with the reviewer and rehearsal state live
    assert cli.main(["resume", str(crashed), "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv"):
        assert (crashed / name).read_bytes() == (reference / name).read_bytes(), name


@pytest.mark.slow
def test_separate_learner_and_reviewer_budgets(tmp_path):
    """A reviewer budget alone makes the budgets separate: the learner keeps steps_per_task (400)."""
    import csv

    out = tmp_path / "run"
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(out), "--no-progress",
                     "train.tensorboard=false", "env.tasks=[room1,room2]", "train.reviewer_steps_per_task=200"]) == 0
    rows = list(csv.DictReader((out / "train.csv").open()))
    last = {r["task"]: r for r in rows}
    assert int(last["room1"]["learner_step"]) == 400 and int(last["room1"]["step"]) == 400
    # Task 2: the learner keeps its full budget; the reviewer stops after its own 200 steps.
    assert int(last["room2"]["learner_step"]) == 400 and int(last["room2"]["step"]) == 600
    reviewer_rows = [r for r in rows if r["task"] == "room2" and r["reviewer_episode_reward"] != ""]
    assert len(reviewer_rows) == 2


@pytest.mark.slow
def test_the_reviewer_is_paid_against_theta_less_the_offset(tmp_path):
    """With an offset of 100 nats every transition scores far above theta - 100, so r_old = c = 1 and each
    of the reviewer's 100 steps is paid 1 - 0.5 = 0.5: 50 an episode, what its reward sums to in train.csv."""
    import csv

    out = tmp_path / "run"
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(out), "--no-progress",
                     "train.tensorboard=false", "env.tasks=[room1,room2]", "method.reviewer.threshold_offset=100"]) == 0
    reviewer = [r for r in csv.DictReader((out / "train.csv").open()) if r["reviewer_episode_reward"] != ""]
    assert reviewer and all(r["task"] == "room2" for r in reviewer)
    for row in reviewer:
        assert float(row["old_model_episode_reward"]) == pytest.approx(100.0, abs=1e-3)
        assert float(row["reviewer_episode_reward"]) == pytest.approx(50.0, abs=1e-3)


@pytest.mark.slow
def test_shared_budget_halves_the_learner_steps_once_a_reviewer_runs(drago_run):
    import csv

    last = {r["task"]: r for r in csv.DictReader((drago_run / "train.csv").open())}
    assert int(last["room1"]["learner_step"]) == 400
    for task in ("room2", "room3", "room4"):
        assert int(last[task]["step"]) == 400 and int(last[task]["learner_step"]) == 200


def test_continuous_count_bonus_is_bounded_where_the_official_one_explodes():
    torch.manual_seed(0)
    counts = ContinuousCounts(obs_dim=5)
    visited = torch.full((1, 5), 0.5)
    for _ in range(20):
        counts.update(visited)
    elsewhere = 2 * torch.randn(1000, 5)
    n = counts.count(elsewhere)
    # Where the last step lowered p the count is 0: the official 1/sqrt(N + 1e-8) would pay 10^4 there.
    assert (n == 0).any()
    bonus = counts.bonus(elsewhere)
    assert torch.all(bonus > 0) and torch.all(bonus <= 1)
    assert torch.allclose(bonus[n == 0], torch.ones(()))


def test_continuous_count_bonus_falls_as_a_state_is_revisited():
    torch.manual_seed(0)
    counts = ContinuousCounts(obs_dim=5)
    visited = torch.full((1, 5), 0.5)
    counts.update(visited)
    counts.update(visited)
    early = counts.bonus(visited).item()
    for _ in range(300):
        counts.update(visited)
    assert counts.bonus(visited).item() < 0.75 * early


def test_continuous_counts_round_trip():
    torch.manual_seed(0)
    counts, other = ContinuousCounts(obs_dim=4), ContinuousCounts(obs_dim=4)
    for _ in range(5):
        counts.update(torch.randn(1, 4))
    other.load_state_dict(copy.deepcopy(counts.state_dict()))
    probe = torch.randn(64, 4)
    assert torch.equal(counts.bonus(probe), other.bonus(probe))
    torch.manual_seed(1)
    counts.update(probe[:1])
    torch.manual_seed(1)
    other.update(probe[:1])
    assert torch.equal(counts.bonus(probe), other.bonus(probe))


# ---------------------------------------------------------------------------------------------------
# Speed: one world-model rollout per gradient step; reduced precision end to end
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_task_two_rolls_the_world_model_once_per_gradient_step(tmp_path, monkeypatch):
    """The learner's update reuses its rows of the reviewer's rollout instead of rolling them again."""
    from drago.agent import agent as agent_module
    from drago.agent import losses as losses_module
    from drago.continual import drago as drago_module

    rollouts, steps = [], []
    original_rollout, original_step = losses_module.rollout, drago_module.Drago.gradient_step

    def counting_rollout(world_model, obs, actions, horizon):
        rollouts.append((len(steps), obs.shape[0], torch.is_grad_enabled()))
        return original_rollout(world_model, obs, actions, horizon)

    def counting_step(self, task, u):
        steps.append(task.index)
        return original_step(self, task, u)

    monkeypatch.setattr(losses_module, "rollout", counting_rollout)
    monkeypatch.setattr(agent_module, "rollout", counting_rollout)
    monkeypatch.setattr(drago_module.Drago, "gradient_step", counting_step)
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(tmp_path / "run"), "--no-progress",
                     "train.tensorboard=false", "env.tasks=[room1,room2]"]) == 0
    B = 32  # the smoke preset's batch
    for index, rows in ((0, B), (1, 2 * B)):
        mine = [r for r in rollouts if steps[r[0] - 1] == index]
        assert len(mine) == steps.count(index) > 0  # exactly one rollout per gradient step
        assert all(n == rows and grad for _, n, grad in mine)  # task 1: learner rows; task 2: 2B rows


@pytest.mark.slow
def test_drago_trains_in_bfloat16(tmp_path):
    import csv

    out = tmp_path / "run"
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(out), "--no-progress",
                     "train.tensorboard=false", "env.tasks=[room1,room2]", "agent.tdmpc.precision=bfloat16"]) == 0
    rows = [r for r in csv.DictReader((out / "train.csv").open()) if r["reviewer_value_loss"]]
    assert rows
    for r in rows:
        for key in ("learner_value_loss", "reviewer_consistency_loss", "reviewer_mean_prediction_score",
                    "vae_loss", "rehearsal_loss", "threshold"):
            assert math.isfinite(float(r[key])), key


def test_reviewer_count_bonus_stays_float32_when_planning_in_bfloat16():
    """Classifier pseudo-counts divide by the change of a probability across one update: bfloat16
    would round it away, so the reviewer's planner evaluates the bonus outside autocast."""
    from drago.agent.agent import Agent

    torch.manual_seed(0)
    counts = ContinuousCounts(obs_dim=3)
    for _ in range(50):
        counts.update(torch.randn(1, 3))
    probe = torch.randn(512, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        rounded = counts.bonus(probe)
    assert (rounded - counts.bonus(probe)).abs().max() > 0.1  # what autocast alone would do

    seen = []

    def bonus(z):
        seen.append((torch.is_autocast_enabled("cpu"), z.dtype))
        return counts.bonus(z)

    cfg = tdmpc_config(mlp_dim=16, horizon=3, iterations=2, num_samples=16, num_elites=4, precision="bfloat16")
    wm = WorldModel(3, 2, 16, use_crelu=False, squash=False)
    reviewer = Agent(wm, torch.optim.Adam(wm.dynamics.parameters()), cfg, discrete=False, reviewer=True)
    reviewer.act(np.zeros(3, dtype=np.float32), step=10**6, eval_mode=False, first_step=True, bonus=bonus)
    assert seen and all(s == (False, torch.float32) for s in seen)
