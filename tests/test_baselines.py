"""The three baselines of paper §4: EWC, bounded replay and curiosity.

The maths is checked on hand-made tensors against closed forms; each method then runs a full `smoke`
sequence, and its task checkpoints are inspected (paper §3.3; docs: Design, how a run flows: carried state, no old heads).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from drago import cli
from drago.agent.agent import Agent
from drago.agent.buffer import Batch, EpisodeReplay
from drago.agent.losses import model_losses, prediction_error
from drago.agent.networks import TaskHeads, WorldModel
from drago.config import load_config
from drago.continual import METHODS
from drago.continual.base import Budget, TaskState
from drago.continual.curiosity import Curiosity
from drago.continual.ewc import EWC, consistency_loss, ewc_penalty, fisher_diagonal, trainable_parameters
from drago.continual.replay import Replay, ReservoirBuffer, replay_loss, replay_weight, stored_transitions
from drago.envs import env_spec
from drago.training.checkpoint import load_checkpoint, save_checkpoint
from helpers import QUIET, SimulatedCrash, crash_at_gradient_step

OBS, ACT, H, MLP = 3, 3, 3, 16
TASKS = ("room1", "room2", "room3", "room4")


def make_world(seed: int = 0) -> WorldModel:
    torch.manual_seed(seed)
    return WorldModel(OBS, ACT, MLP, use_crelu=True, squash=True)


def make_batch(seed: int, batch: int = 8, horizon: int = H) -> Batch:
    g = torch.Generator().manual_seed(seed)
    return Batch(obs=torch.rand(batch, OBS, generator=g) * 2 - 1,
                 actions=F.one_hot(torch.randint(0, ACT, (horizon + 1, batch), generator=g), ACT).float(),
                 rewards=torch.rand(horizon + 1, batch, generator=g) * 2 - 1,
                 next_obs=torch.rand(horizon + 1, batch, OBS, generator=g) * 2 - 1,
                 weights=torch.ones(batch), indices=np.arange(batch))


def shifted(model: WorldModel, direction: dict[str, torch.Tensor], alpha: float) -> WorldModel:
    """A copy of ``model`` moved by ``alpha * direction`` in parameter space."""
    moved = make_world()
    moved.load_state_dict(model.state_dict())
    with torch.no_grad():
        for name, p in trainable_parameters(moved).items():
            p += alpha * direction[name]
    return moved


def nested_equal(a, b) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(nested_equal(a[k], b[k]) for k in a)
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    return a == b


def key_paths(value, prefix: str = "") -> list[str]:
    if not isinstance(value, dict):
        return []
    out = []
    for k, v in value.items():
        out.append(f"{prefix}{k}")
        out.extend(key_paths(v, f"{prefix}{k}."))
    return out


# ---------------------------------------------------------------------------------------------------
# EWC
# ---------------------------------------------------------------------------------------------------
def test_ewc_penalty_is_zero_at_anchor_quadratic_in_distance_and_fisher_weighted():
    model = make_world()
    params = trainable_parameters(model)
    assert params and all(name.startswith("dynamics.") for name in params)  # the EMA target is not penalised
    anchor = {k: p.detach().clone() for k, p in params.items()}
    g = torch.Generator().manual_seed(3)
    fisher = {k: torch.rand(p.shape, generator=g) for k, p in params.items()}
    direction = {k: torch.randn(p.shape, generator=g) for k, p in params.items()}

    assert ewc_penalty(model, [anchor], [fisher]).item() == 0.0  # exactly, not approximately
    expected_unit = sum(float((fisher[k].double() * direction[k].double() ** 2).sum()) for k in params)
    values = {a: ewc_penalty(shifted(model, direction, a), [anchor], [fisher]).item() for a in (0.01, 0.02, 0.1)}
    for alpha, value in values.items():
        assert value == pytest.approx(alpha**2 * expected_unit, rel=1e-4)
    assert values[0.02] / values[0.01] == pytest.approx(4.0, rel=1e-3)  # quadratic, not linear

    far = shifted(model, direction, 1.0)
    zero = {k: torch.zeros_like(f) for k, f in fisher.items()}
    assert ewc_penalty(far, [anchor], [zero]).item() == 0.0
    # The Fisher weighs each coordinate: doubling it doubles the penalty, and a Fisher on one tensor
    # only sees the distance along that tensor.
    doubled = {k: 2 * f for k, f in fisher.items()}
    assert ewc_penalty(far, [anchor], [doubled]).item() == pytest.approx(2 * ewc_penalty(far, [anchor], [fisher]).item())
    only = next(iter(params))
    one = {k: (f if k == only else torch.zeros_like(f)) for k, f in fisher.items()}
    assert ewc_penalty(far, [anchor], [one]).item() == pytest.approx(float((fisher[only] * direction[only] ** 2).sum()),
                                                                      rel=1e-4)
    # Several (anchor, Fisher) pairs add up.
    pair_sum = ewc_penalty(far, [anchor, anchor], [fisher, one]).item()
    assert pair_sum == pytest.approx(ewc_penalty(far, [anchor], [fisher]).item() + ewc_penalty(far, [anchor], [one]).item())
    # And the penalty trains the world model back towards the anchor.
    penalty = ewc_penalty(far, [anchor], [fisher])
    penalty.backward()
    for name, p in trainable_parameters(far).items():
        assert torch.allclose(p.grad, 2 * fisher[name] * direction[name], atol=1e-5)


class PartlyUsed(nn.Module):
    """A world-model double with one parameter the loss never reads."""

    def __init__(self):
        super().__init__()
        self.dynamics = nn.Linear(OBS + ACT, OBS)
        self.unused = nn.Parameter(torch.ones(5))

    def encode(self, obs):
        return obs

    def forward(self, z, a):
        return torch.tanh(self.dynamics(torch.cat((z, a), -1)))


def test_fisher_is_mean_squared_batch_gradient_nonnegative_and_zero_where_the_loss_does_not_look():
    model = make_world()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    batches = [make_batch(seed) for seed in range(3)]
    fisher = fisher_diagonal(model, batches, horizon=H, rho=0.5)
    params = trainable_parameters(model)
    assert fisher.keys() == params.keys()
    assert all(f.shape == params[k].shape and (f >= 0).all() and torch.isfinite(f).all() for k, f in fisher.items())
    assert sum(float(f.sum()) for f in fisher.values()) > 0
    assert all(p.grad is None for p in params.values())  # no .grad written
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # model untouched

    # Closed form: mean over batches of the squared gradient of sum_t rho^t mse_t (batch mean).
    expected = {k: torch.zeros_like(p) for k, p in params.items()}
    for b in batches:
        model.zero_grad()
        z, loss = b.obs, 0.0
        for t in range(H):
            z = model(z, b.actions[t])
            loss = loss + 0.5**t * ((z - b.next_obs[t]) ** 2).mean(-1)
        loss.mean().backward()
        for k, p in params.items():
            expected[k] += p.grad**2 / len(batches)
    for k in params:
        assert torch.allclose(fisher[k], expected[k], rtol=1e-5, atol=1e-12), k

    double = PartlyUsed()
    fisher = fisher_diagonal(double, batches, horizon=H)
    assert torch.equal(fisher["unused"], torch.zeros(5))
    assert (fisher["dynamics.weight"] > 0).any()
    # At a perfect prediction the loss is flat: a zero Fisher.
    target = make_batch(9)
    with torch.no_grad():
        z = target.obs
        for t in range(H):
            z = double(z, target.actions[t])
            target.next_obs[t] = z
    assert all(float(f.abs().max()) == 0.0 for f in fisher_diagonal(double, [target], horizon=H).values())
    with pytest.raises(ValueError):
        fisher_diagonal(model, [], horizon=H)


def test_consistency_loss_matches_the_learner_update():
    """The Fisher's loss is the consistency term of model_losses (paper §2; docs: Design, the agent), per sample."""
    model, batch = make_world(), make_batch(4)
    heads = TaskHeads(OBS, ACT, MLP, discrete=True)
    losses = model_losses(model, heads, batch.obs, batch.actions, batch.rewards, batch.next_obs, horizon=H, rho=0.5,
                          discount=0.99, policy_std=0.05, consistency_coef=2.0, reward_coef=0.5, value_coef=0.1,
                          first_step_qr_only=False, train_world_model=True)
    mine = consistency_loss(model, batch.obs, batch.actions, batch.next_obs, H, 0.5)
    assert torch.allclose(mine, losses.consistency)


# ---------------------------------------------------------------------------------------------------
# Bounded replay
# ---------------------------------------------------------------------------------------------------
def offer_ids(buffer: ReservoirBuffer, ids: np.ndarray, task: int = 0) -> None:
    """Offer transitions whose first observation coordinate is a unique item id."""
    obs = torch.zeros(len(ids), OBS)
    obs[:, 0] = torch.as_tensor(ids, dtype=torch.float32)
    buffer.offer(obs, torch.zeros(len(ids), ACT), obs + 0.5, task=task)


def test_reservoir_never_exceeds_budget_and_keeps_every_task():
    capacity = 2163  # paper §2; docs: Design, the agent: floats of the grid VAE / 10 floats per transition
    buffer = ReservoirBuffer(capacity, OBS, ACT, np.random.default_rng(0))
    for task in range(4):
        for chunk in np.array_split(np.arange(task * 5000, (task + 1) * 5000), 7):  # episodes of uneven size
            offer_ids(buffer, chunk, task)
            assert len(buffer) <= capacity and buffer.obs.shape[0] == capacity
        assert len(buffer) == capacity
        counts = buffer.task_counts()
        assert sorted(counts) == list(range(task + 1)) and sum(counts.values()) == capacity
        for share in counts.values():  # tasks so far share the budget equally in expectation
            assert share / capacity == pytest.approx(1 / (task + 1), abs=0.05)
    assert buffer.seen == 20_000
    # Every held row is a real offered transition (s, a, s') of the task its tag says.
    ids = buffer.obs[:, 0].long()
    assert torch.equal(ids // 5000, buffer.tasks)
    assert torch.equal(buffer.next_obs, buffer.obs + 0.5)
    assert len(torch.unique(ids)) == capacity  # no transition stored twice


def test_reservoir_inclusion_is_uniform_over_all_offers():
    """Each of 500 items offered in uneven calls (one straddling the fill point) is kept with
    probability 50/500: a chi-square test on 2,000 runs with a fixed seed."""
    capacity, n, trials = 50, 500, 2000
    rng = np.random.default_rng(1234)
    counts = np.zeros(n)
    chunks = np.split(np.arange(n), [30, 100, 260])
    for _ in range(trials):
        buffer = ReservoirBuffer(capacity, OBS, ACT, rng)
        for task, chunk in enumerate(chunks):
            offer_ids(buffer, chunk, task)
        counts[buffer.obs[:, 0].long().numpy()] += 1
    expected = trials * capacity / n
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    dof = n - 1
    assert abs(chi2 - dof) < 5 * math.sqrt(2 * dof), chi2
    # No order bias: early, straddling and late offers are kept equally often.
    for chunk in chunks:
        mean, sd = counts[chunk].mean(), math.sqrt(expected * (1 - capacity / n) / len(chunk))
        assert abs(mean - expected) < 5 * sd, (chunk[0], mean)


def test_reservoir_state_round_trips_through_a_checkpoint(tmp_path):
    buffer = ReservoirBuffer(40, OBS, ACT, np.random.default_rng(5))
    offer_ids(buffer, np.arange(100), 0)
    path = save_checkpoint(tmp_path / "r.pt", {"method": {"reservoir": buffer.state_dict()}}, kind="task",
                           domain="minigrid")
    restored = ReservoirBuffer(40, OBS, ACT, np.random.default_rng(99))
    restored.load_state_dict(load_checkpoint(path, kind="task")["method"]["reservoir"])
    assert nested_equal(restored.state_dict(), buffer.state_dict())
    # The generator state came along: both make the same decisions from here on.
    for b in (buffer, restored):
        offer_ids(b, np.arange(100, 300), 1)
    assert nested_equal(restored.state_dict(), buffer.state_dict())
    with pytest.raises(ValueError):
        ReservoirBuffer(41, OBS, ACT, np.random.default_rng(0)).load_state_dict(buffer.state_dict())


def test_stored_transitions_pair_every_step_with_its_successor():
    length = 6
    buf = EpisodeReplay(3 * length, OBS, ACT, horizon=2, episode_length=length)
    episodes = []
    for e in range(2):
        obs = np.arange((length + 1) * OBS, dtype=np.float32).reshape(length + 1, OBS) + 100 * e
        act = np.eye(ACT, dtype=np.float32)[np.arange(length) % ACT]
        buf.add_episode(obs, act, np.zeros(length, dtype=np.float32))
        episodes.append((obs, act))
    s, a, s_next = stored_transitions(buf)
    assert s.shape == (2 * length, OBS) and a.shape == (2 * length, ACT) and s_next.shape == (2 * length, OBS)
    for e, (obs, act) in enumerate(episodes):
        rows = slice(e * length, (e + 1) * length)
        assert torch.equal(s[rows], torch.as_tensor(obs[:-1]))
        assert torch.equal(s_next[rows], torch.as_tensor(obs[1:]))
        assert torch.equal(a[rows], torch.as_tensor(act))


def test_replay_weight_makes_old_rows_the_configured_share():
    assert replay_weight(2.0, 10, 0.5) == pytest.approx(0.2)  # one old row weighs as one new first step
    assert replay_weight(2.0, 10, 0.0) == 0.0
    assert replay_weight(1.0, 1, 0.75) == pytest.approx(3.0)
    with pytest.raises(ValueError):
        replay_weight(2.0, 10, 1.0)
    model, batch = make_world(), make_batch(6)
    loss = replay_loss(model, batch.obs, batch.actions[0], batch.next_obs[0])
    assert torch.allclose(loss, prediction_error(model(batch.obs, batch.actions[0]), batch.next_obs[0]).mean())


# ---------------------------------------------------------------------------------------------------
# Curiosity
# ---------------------------------------------------------------------------------------------------
def test_curiosity_bonus_raises_the_td_target_by_c_times_prediction_error():
    model, batch = make_world(), make_batch(7, batch=5)
    torch.manual_seed(1)
    heads = TaskHeads(OBS, ACT, MLP, discrete=True)  # zero last layers: Q = Q_target = 0 at init
    c, rho = 0.7, 0.5

    def losses(coef):
        return model_losses(model, heads, batch.obs, batch.actions, batch.rewards, batch.next_obs, horizon=H,
                            rho=rho, discount=0.99, policy_std=0.05, consistency_coef=2.0, reward_coef=0.5,
                            value_coef=0.1, first_step_qr_only=False, train_world_model=True, curiosity_coef=coef)

    plain, curious = losses(0.0), losses(c)
    with torch.no_grad():
        z, errors = batch.obs, []
        for t in range(H):
            z = model(z, batch.actions[t])
            errors.append(((z - batch.next_obs[t]) ** 2).mean(-1))  # open-loop e_t
    e = torch.stack(errors)
    for coef, result in ((0.0, plain), (c, curious)):
        td = batch.rewards[:H] + coef * e  # + gamma * 0
        weights = rho ** torch.arange(H, dtype=torch.float32)[:, None]
        assert torch.allclose(result.value, (weights * 2 * td**2).sum(0), rtol=1e-5)
        assert torch.allclose(result.priority, (weights * 2 * td.abs()).sum(0), rtol=1e-5)
    assert torch.equal(plain.reward, curious.reward)  # the reward head still fits the env reward
    assert torch.equal(plain.consistency, curious.consistency)


# ---------------------------------------------------------------------------------------------------
# The methods' hooks on a hand-built task
# ---------------------------------------------------------------------------------------------------
def make_task(cfg, index: int = 0, seed: int = 0) -> TaskState:
    spec = env_spec("minigrid")
    torch.manual_seed(seed)
    model = WorldModel(spec.obs_dim, spec.action_dim, cfg.agent.tdmpc.mlp_dim, cfg.agent.tdmpc.use_crelu, squash=True)
    optimizer = torch.optim.Adam(model.dynamics.parameters(), lr=cfg.agent.lr)
    learner = Agent(model, optimizer, cfg.agent, discrete=True)
    L = cfg.env.episode_length
    buffer = EpisodeReplay(2 * L, spec.obs_dim, spec.action_dim, cfg.agent.tdmpc.horizon, L)
    rng = np.random.default_rng(seed)
    for _ in range(2):
        buffer.add_episode(rng.uniform(-1, 1, (L + 1, spec.obs_dim)), np.eye(3)[rng.integers(0, 3, L)],
                           rng.uniform(0, 1, L))
    return TaskState(index=index, name=TASKS[index], world_model=model, world_optimizer=optimizer, learner=learner,
                     buffer=buffer, rng=rng, env=None, budget=Budget.from_config(cfg))


def record_update(task: TaskState, monkeypatch) -> list[dict]:
    calls = []
    real = task.learner.update

    def update(batch, step, **kwargs):
        calls.append(kwargs)
        return real(batch, step, **kwargs)

    monkeypatch.setattr(task.learner, "update", update)
    return calls


@pytest.fixture
def smoke_cfg():
    # One config for several methods: each reads its own section.
    return load_config("smoke", ["train.tensorboard=false", "method.ewc.fisher_batches=3"], inapplicable_ok=True)


def test_curiosity_passes_its_coefficient_to_the_learner(smoke_cfg, monkeypatch):
    smoke_cfg.method.curiosity.coef = 0.3
    method, task = Curiosity(smoke_cfg, env_spec("minigrid"), torch.device("cpu")), make_task(smoke_cfg)
    calls = record_update(task, monkeypatch)
    metrics = method.gradient_step(task, 0)
    assert calls[-1]["curiosity_coef"] == 0.3 and calls[-1].get("world_model_loss") is None
    assert "learner_value_loss" in metrics and "learner_priority" not in metrics


def test_ewc_penalises_only_after_a_task_and_carries_fisher_and_anchor(smoke_cfg, monkeypatch, tmp_path):
    spec, device = env_spec("minigrid"), torch.device("cpu")
    method, task = EWC(smoke_cfg, spec, device), make_task(smoke_cfg)
    calls = record_update(task, monkeypatch)
    method.gradient_step(task, 0)
    assert calls[-1]["world_model_loss"] is None and method.carry_state() == {}
    method.end_task(task)
    first = method.carry_state()
    assert first["tasks"] == 1
    assert first["anchor"].keys() == first["fisher"].keys() == trainable_parameters(task.world_model).keys()
    assert all(torch.equal(first["anchor"][k], p.detach()) for k, p in trainable_parameters(task.world_model).items())

    # The next task starts from the anchor: zero penalty, then it grows as the model moves.
    nxt = make_task(smoke_cfg, index=1, seed=1)
    nxt.world_model.load_state_dict(task.world_model.state_dict())
    calls = record_update(nxt, monkeypatch)
    assert method.penalty(nxt.world_model).item() == 0.0
    metrics = method.gradient_step(nxt, 0)
    assert callable(calls[-1]["world_model_loss"]) and float(metrics["learner_world_model_extra_loss"]) == 0.0
    for u in range(1, 4):
        method.gradient_step(nxt, u)
    expected = 0.5 * smoke_cfg.method.ewc.coef * ewc_penalty(nxt.world_model, [first["anchor"]], [first["fisher"]])
    assert method.penalty(nxt.world_model).item() == pytest.approx(expected.item()) and expected.item() > 0

    # Accumulated Fisher, latest anchor.
    method.end_task(nxt)
    second = method.carry_state()
    assert second["tasks"] == 2
    for k, p in trainable_parameters(nxt.world_model).items():
        assert torch.equal(second["anchor"][k], p.detach())
        assert (second["fisher"][k] >= first["fisher"][k]).all()

    path = save_checkpoint(tmp_path / "c.pt", {"method": second}, kind="task", domain="minigrid")
    restored = EWC(smoke_cfg, spec, device)
    restored.load_carry_state(load_checkpoint(path, kind="task")["method"])
    assert nested_equal(restored.carry_state(), second)


def test_replay_mixes_old_rows_only_after_a_task_and_carries_the_reservoir(smoke_cfg, monkeypatch, tmp_path):
    spec, device = env_spec("minigrid"), torch.device("cpu")
    method, task = Replay(smoke_cfg, spec, device), make_task(smoke_cfg)
    calls = record_update(task, monkeypatch)
    method.gradient_step(task, 0)
    assert calls[-1]["world_model_loss"] is None
    method.end_task(task)
    assert len(method.reservoir) == len(task.buffer) and method.reservoir.task_counts() == {0: len(task.buffer)}

    nxt = make_task(smoke_cfg, index=1, seed=1)
    calls = record_update(nxt, monkeypatch)
    metrics = method.gradient_step(nxt, 0)
    assert callable(calls[-1]["world_model_loss"]) and float(metrics["learner_world_model_extra_loss"]) > 0

    path = save_checkpoint(tmp_path / "c.pt", {"method": method.carry_state()}, kind="task", domain="minigrid")
    restored = Replay(smoke_cfg, spec, device)
    restored.load_carry_state(load_checkpoint(path, kind="task")["method"])
    assert nested_equal(restored.carry_state(), method.carry_state())


# ---------------------------------------------------------------------------------------------------
# End to end on the smoke preset
# ---------------------------------------------------------------------------------------------------
EXTRA = {"replay": ["method.replay.capacity=500"]}  # below 4 x 400 transitions: replacement happens


@pytest.fixture(scope="module")
def runs(smoke_runs):
    """One complete smoke run per method, made on first use and shared by the tests."""
    cache: dict[str, Path] = {}

    def get(method: str) -> Path:
        if method not in cache:
            cache[method] = smoke_runs(method, *EXTRA.get(method, []))
        return cache[method]

    return get


def checkpoints(run: Path) -> list[dict]:
    return [load_checkpoint(run / "checkpoints" / f"task{i + 1}_{t}.pt", kind="task", domain="minigrid")
            for i, t in enumerate(TASKS)]


@pytest.mark.slow
@pytest.mark.parametrize("method", ["ewc", "replay", "curiosity"])
def test_smoke_sequence_carries_the_method_state_and_no_heads(method, runs):
    run = runs(method)
    rows = list(csv.DictReader((run / "train.csv").open(newline="")))
    assert [r["task"] for r in rows] == [t for t in TASKS for _ in range(4)]
    head_keys = set(TaskHeads(OBS, ACT, 32, discrete=True).state_dict())
    world_keys = set(make_world().state_dict())
    for index, data in enumerate(checkpoints(run)):
        assert set(data["learner"]) == head_keys  # the trainer's own copy, never read by the next task
        rest = {k: v for k, v in data.items() if k not in ("learner", "config")}
        for path in key_paths(rest):
            assert not any(path == k or path.endswith(f".{k}") for k in head_keys), path
            assert not any(word in path for word in ("optimizer", "exp_avg", "policy", "q_target")), path
        assert set(data["world_model"]) == world_keys
        state = data["method"]
        if method == "ewc":
            assert state["tasks"] == index + 1
            assert set(state["fisher"]) == set(state["anchor"]) == {k for k in world_keys if k.startswith("dynamics.")}
            for k, v in state["anchor"].items():  # the anchor is the world model the task ended with
                assert torch.equal(v, data["world_model"][k])
        elif method == "replay":
            reservoir = state["reservoir"]
            assert reservoir["seen"] == 400 * (index + 1) and reservoir["capacity"] == 500
            assert reservoir["obs"].shape == (min(400 * (index + 1), 500), OBS)
            assert set(reservoir["tasks"].tolist()) == set(range(index + 1))  # every finished task is represented
        else:
            assert state == {}
    # The extra world-model loss is logged exactly where it applies: after the first task's seed phase.
    if method in ("ewc", "replay"):
        for r in rows:
            has_loss = r["learner_total_loss"] != ""
            assert (r.get("learner_world_model_extra_loss", "") != "") == (has_loss and r["task"] != "room1"), r


@pytest.mark.slow
def test_replay_resumed_mid_task_matches_the_uninterrupted_run(runs, tmp_path):
    reference = runs("replay")
    crashed = tmp_path / "crashed"
    # inside episode 4 of task 3, after the periodic checkpoint at step 200
    with crash_at_gradient_step(Replay, 16, task=2), pytest.raises(SimulatedCrash):
        cli.main(["train", "smoke", "--method", "replay", "--out", str(crashed), *QUIET, *EXTRA["replay"]])
    assert load_checkpoint(crashed / "checkpoints" / "resume.pt", kind="resume")["task_index"] == 2
    assert cli.main(["resume", str(crashed), "--no-progress"]) == 0
    for mine, ref in zip(checkpoints(crashed), checkpoints(reference)):
        assert nested_equal(mine["method"], ref["method"])
        assert nested_equal(mine["world_model"], ref["world_model"])
    for name in ("train.csv", "eval.csv"):
        assert (crashed / name).read_bytes() == (reference / name).read_bytes(), name


def test_methods_are_registered():
    for name, cls in (("ewc", EWC), ("replay", Replay), ("curiosity", Curiosity)):
        assert METHODS[name] is cls and cls.name == name and cls.description
