"""PETS core (drago.agent.pets): objective, bootstrap, trajectory sampling, CEM and the agent surface."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import nn

from drago.agent.pets import (
    PetsAgent,
    PetsConfig,
    PetsPlanSettings,
    ProbabilisticEnsemble,
    bootstrap_indices,
    cem,
    gaussian_nll,
    logvar_bound_penalty,
    make_optimizer,
    plan,
    propagate,
    soft_clamp_logvar,
)


def _softplus(x: float) -> float:
    return math.log1p(math.exp(x))


# ----------------------------------------------------------------------------- objective
def test_gaussian_nll_matches_hand_computation():
    mean = torch.tensor([[1.0, 2.0], [0.0, -1.0]])
    logvar = torch.tensor([[0.0, math.log(2.0)], [math.log(4.0), 0.0]])
    target = torch.zeros(2, 2)
    # Row 0: 1*1 + 0 and 4/2 + ln 2; row 1: 0/4 + ln 4 and 1*1 + 0.
    expected = (1.0 + (2.0 + math.log(2.0)) + math.log(4.0) + 1.0) / 4
    assert gaussian_nll(mean, logvar, target).item() == pytest.approx(expected, abs=1e-6)
    # (E, B, D): one value per member.
    stacked = gaussian_nll(torch.stack((mean, mean + 1)), torch.stack((logvar, logvar)), torch.stack((target, target)))
    assert stacked.shape == (2,)
    assert stacked[0].item() == pytest.approx(expected, abs=1e-6)
    # mean + 1: row 0 is 4*1 + 0 and 9/2 + ln 2; row 1 is 1/4 + ln 4 and 0*1 + 0.
    shifted = (4.0 + (9.0 / 2 + math.log(2.0)) + (1.0 / 4 + math.log(4.0)) + 0.0) / 4
    assert stacked[1].item() == pytest.approx(shifted, abs=1e-6)


def test_bound_penalty_value_and_gradient_direction():
    max_logvar = torch.tensor([[0.5, 1.0]], requires_grad=True)
    min_logvar = torch.tensor([[-10.0, -2.0]], requires_grad=True)
    penalty = logvar_bound_penalty(max_logvar, min_logvar)
    assert penalty.item() == pytest.approx(0.01 * (1.5 - (-12.0)))
    penalty.backward()
    assert torch.allclose(max_logvar.grad, torch.full((1, 2), 0.01))
    assert torch.allclose(min_logvar.grad, torch.full((1, 2), -0.01))
    # A descent step moves max down and min up.
    opt = torch.optim.SGD([max_logvar, min_logvar], lr=1.0)
    opt.step()
    assert (max_logvar < torch.tensor([[0.5, 1.0]])).all() and (min_logvar > torch.tensor([[-10.0, -2.0]])).all()


def test_soft_clamp_logvar_bounds():
    max_logvar, min_logvar = torch.tensor([[0.5]]), torch.tensor([[-10.0]])
    raw = torch.tensor([[1e3], [50.0], [-50.0], [-1e3], [0.0], [-3.0], [-5.0]])
    out = soft_clamp_logvar(raw, max_logvar, min_logvar)
    assert (out <= 0.5 + 1e-3).all() and (out >= -10.0).all()
    assert out[0].item() == pytest.approx(0.5, abs=1e-3) and out[3].item() == pytest.approx(-10.0, abs=1e-3)
    # Hand computation at raw = 0.
    first = 0.5 - _softplus(0.5)
    assert out[4].item() == pytest.approx(-10.0 + _softplus(first + 10.0), abs=1e-5)
    # Well inside the bounds it is nearly the identity.
    assert torch.allclose(out[5:], raw[5:], atol=0.05)


def test_ensemble_loss_is_member_sum_plus_penalty_and_bounds_get_gradients():
    torch.manual_seed(0)
    model = ProbabilisticEnsemble(2, 1, members=3, hidden=8, layers=2)
    obs, act, nxt, rew = torch.randn(6, 2), torch.randn(6, 1), torch.randn(6, 2), torch.randn(6)
    loss, metrics = model.loss(obs, act, nxt, rew)
    mean, logvar = model(obs, act)
    target = torch.cat((nxt - obs, rew[:, None]), -1).expand(3, -1, -1)
    expected = gaussian_nll(mean, logvar, target).sum() + logvar_bound_penalty(model.max_logvar, model.min_logvar)
    assert loss.item() == pytest.approx(expected.item(), rel=1e-6)
    assert metrics["nll"].item() == pytest.approx(gaussian_nll(mean, logvar, target).mean().item(), rel=1e-6)
    loss.backward()
    assert model.max_logvar.grad is not None and model.min_logvar.grad is not None


# ----------------------------------------------------------------------------- bootstrap
def test_bootstrap_indices_shapes_and_generators():
    idx = bootstrap_indices(10, 4, np.random.default_rng(0))
    assert idx.shape == (4, 10) and idx.dtype == torch.long and idx.min() >= 0 and idx.max() < 10
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(bootstrap_indices(10, 4, g1), bootstrap_indices(10, 4, g2))
    big = bootstrap_indices(200, 3, torch.Generator().manual_seed(0))
    assert not torch.equal(big[0], big[1])  # each member its own draw
    assert len(torch.unique(big[0])) < 200  # with replacement


def _member_grads(model: ProbabilisticEnsemble, k: int) -> list[torch.Tensor]:
    return [p.grad[k].clone() for layer in (*model.hidden, model.head) for p in (layer.weight, layer.bias)]


def test_each_member_sees_only_its_bootstrap_rows():
    torch.manual_seed(0)
    model = ProbabilisticEnsemble(2, 1, members=2, hidden=8, layers=2)
    n = 8
    obs, act, nxt, rew = torch.randn(n, 2), torch.randn(n, 1), torch.randn(n, 2), torch.randn(n)
    indices = torch.tensor([[0, 0, 1, 2, 3, 3, 1, 2], [4, 5, 6, 7, 7, 4, 5, 6]])
    poisoned_nxt, poisoned_rew = nxt.clone(), rew.clone()
    poisoned_nxt[4:] = 1e3
    poisoned_rew[4:] = -1e3

    grads = []
    for target, reward in ((nxt, rew), (poisoned_nxt, poisoned_rew)):
        model.zero_grad()
        model.loss(obs, act, target, reward, indices)[0].backward()
        grads.append((_member_grads(model, 0), _member_grads(model, 1)))
    for clean, poisoned in zip(grads[0][0], grads[1][0]):
        assert torch.equal(clean, poisoned)  # member 0 never drew rows 4..7
    assert any(not torch.allclose(c, p) for c, p in zip(grads[0][1], grads[1][1]))


def test_train_step_uses_one_bootstrap_draw_per_member():
    n, members = 12, 3
    obs, act, nxt, rew = torch.randn(n, 2), torch.randn(n, 1), torch.randn(n, 2), torch.randn(n)
    drawn = bootstrap_indices(n, members, torch.Generator().manual_seed(5))
    unseen = torch.ones(n, dtype=torch.bool)
    unseen[drawn[0]] = False
    assert unseen.any()
    poisoned = nxt.clone()
    poisoned[unseen] = 1e3

    after = []
    for target in (nxt, poisoned):
        torch.manual_seed(0)
        model = ProbabilisticEnsemble(2, 1, members=members, hidden=8, layers=2)
        opt = make_optimizer(model, lr=1e-2)
        metrics = model.update(obs, act, target, rew, torch.Generator().manual_seed(5), optimizer=opt,
                               update_stats=False)
        assert set(metrics) >= {"nll", "mse", "logvar", "loss"} and all(isinstance(v, float) for v in metrics.values())
        after.append([layer.weight.detach()[0].clone() for layer in (*model.hidden, model.head)])
    for clean, dirty in zip(*after):
        assert torch.equal(clean, dirty)


def test_input_stats_are_the_training_rows_statistics():
    model = ProbabilisticEnsemble(2, 1, members=2, hidden=4, layers=1)
    obs, act = torch.randn(30, 2) * 3 + 1, torch.randn(30, 1)
    model.update_input_stats(obs[:10], act[:10])
    model.update_input_stats(obs[10:], act[10:])
    rows = torch.cat((obs, act), -1)
    assert torch.allclose(model.input_mean, rows.mean(0), atol=1e-5)
    assert torch.allclose(model.input_var, rows.var(0, unbiased=False), atol=1e-4)
    assert model.input_count.item() == 30
    model.fit_input_stats(obs[:5], act[:5])
    assert torch.allclose(model.input_mean, rows[:5].mean(0), atol=1e-6) and model.input_count.item() == 5
    # A constant input dimension is left unscaled.
    model.fit_input_stats(torch.ones(4, 2), torch.zeros(4, 1))
    assert torch.equal(model.input_std(), torch.ones(3))


def test_make_optimizer_decays_weights_only():
    model = ProbabilisticEnsemble(2, 1, members=2, hidden=4, layers=1)
    opt = make_optimizer(model, lr=1e-3, weight_decay=1e-4)
    decayed, free = opt.param_groups
    assert decayed["weight_decay"] == 1e-4 and free["weight_decay"] == 0.0
    assert any(p is model.max_logvar for p in free["params"])
    assert not any(p is model.max_logvar for p in decayed["params"])
    assert len(decayed["params"]) + len(free["params"]) == len(list(model.parameters()))


# ----------------------------------------------------------------------------- trajectory sampling
class ConstantMembers(nn.Module):
    """Member e predicts delta = reward = e + 1 with (practically) no noise."""

    def __init__(self, members: int, obs_dim: int = 1, action_dim: int = 1):
        super().__init__()
        self.members, self.obs_dim, self.action_dim, self.predict_reward = members, obs_dim, action_dim, True
        self.register_buffer("values", torch.arange(1, members + 1, dtype=torch.float32))

    def forward(self, obs, action):
        if obs.dim() == 2:
            obs = obs.unsqueeze(0).expand(self.members, -1, -1)
        mean = self.values.view(-1, 1, 1).expand(obs.shape[0], obs.shape[1], self.obs_dim + 1).clone()
        return mean, torch.full_like(mean, -60.0)


@pytest.mark.parametrize("particles", [8, 6])  # balanced (E divides P) and not
def test_tsinf_particles_keep_one_member(particles):
    members, count, horizon = 4, 3, 6
    model = ConstantMembers(members)
    out = propagate(model, torch.zeros(count, 1), torch.zeros(horizon, count, 1), particles, "tsinf",
                    torch.Generator().manual_seed(0))
    assert out.states.shape == (horizon + 1, count, particles, 1)
    assert out.rewards.shape == out.members.shape == (horizon, count, particles)
    assert (out.members == out.members[0]).all()
    value = (out.members + 1).float()
    assert torch.allclose(out.states[1:, ..., 0] - out.states[:-1, ..., 0], value, atol=1e-5)
    assert torch.allclose(out.rewards, value, atol=1e-5)
    if particles % members == 0:
        counts = torch.stack([(out.members[0] == e).sum(-1) for e in range(members)], -1)
        assert (counts == particles // members).all()
    assert len(torch.unique(out.members[0])) > 1


def test_ts1_particles_switch_members():
    members, count, particles, horizon = 4, 3, 8, 6
    model = ConstantMembers(members)
    out = propagate(model, torch.zeros(count, 1), torch.zeros(horizon, count, 1), particles, "ts1",
                    torch.Generator().manual_seed(0))
    switched = (out.members != out.members[0]).any(0)
    assert switched.float().mean() > 0.5
    value = (out.members + 1).float()
    assert torch.allclose(out.states[1:, ..., 0] - out.states[:-1, ..., 0], value, atol=1e-5)
    for t in range(horizon):  # balanced at every step
        assert all(((out.members[t] == e).sum(-1) == particles // members).all() for e in range(members))


def test_propagate_known_reward_clamp_and_bad_mode():
    model = ConstantMembers(2)
    seen = {}

    def reward(s, a, s2):
        seen["shapes"] = (s.shape, a.shape, s2.shape)
        return torch.full(s.shape[:1], 7.0)

    out = propagate(model, torch.zeros(1), torch.zeros(3, 5, 1), 4, known_reward=reward, state_bounds=(-1.0, 1.0))
    assert (out.rewards == 7.0).all() and seen["shapes"] == ((20, 1), (20, 1), (20, 1))
    assert out.states.max() <= 1.0 and out.states[-1].eq(1.0).all()
    with pytest.raises(ValueError):
        propagate(model, torch.zeros(1, 1), torch.zeros(2, 1, 1), 2, mode="ts2")


def test_propagate_samples_from_the_predicted_gaussian():
    class Noisy(ConstantMembers):
        def forward(self, obs, action):
            mean, _ = super().forward(obs, action)
            return torch.zeros_like(mean), torch.zeros_like(mean)  # unit variance

    out = propagate(Noisy(2), torch.zeros(1, 1), torch.zeros(1, 1, 1), 4000, generator=torch.Generator().manual_seed(0))
    step = out.states[1, 0, :, 0]
    assert abs(step.mean().item()) < 0.1 and abs(step.std().item() - 1.0) < 0.1


# ----------------------------------------------------------------------------- planning
class ActionReward(nn.Module):
    """Static state; reward a function of the action alone, no noise."""

    def __init__(self, reward_fn, action_dim: int, members: int = 2):
        super().__init__()
        self.members, self.obs_dim, self.action_dim, self.predict_reward = members, 1, action_dim, True
        self.reward_fn = reward_fn

    def forward(self, obs, action):
        if obs.dim() == 2:
            obs, action = obs.expand(self.members, -1, -1), action.expand(self.members, -1, -1)
        mean = torch.cat((torch.zeros_like(obs), self.reward_fn(action)[..., None]), -1)
        return mean, torch.full_like(mean, -60.0)


SMALL = {"horizon": 3, "iterations": 4, "population": 48, "elites": 6, "particles": 2}


def _one_hot_rows(action: torch.Tensor) -> bool:
    return bool(((action == 0) | (action == 1)).all() and (action.sum(-1) == 1).all())


def test_discrete_cem_finds_the_best_action_and_returns_one_hots():
    weights = torch.tensor([0.0, 0.2, 1.0])
    model = ActionReward(lambda a: a @ weights, 3)
    s = PetsPlanSettings(**SMALL)
    g = torch.Generator().manual_seed(0)
    action = plan(model, torch.zeros(1), s, discrete=True, eval_mode=True, generator=g)
    assert torch.equal(action, torch.tensor([0.0, 0.0, 1.0]))
    batch = cem(model, torch.zeros(4, 1), s, discrete=True, eval_mode=False, generator=g)
    assert batch.action.shape == (4, 3) and _one_hot_rows(batch.action)
    assert batch.mean.shape == (3, 4, 3) and torch.allclose(batch.mean.sum(-1), torch.ones(3, 4))
    # Flat returns (NaN too): still a valid one-hot.
    flat = ActionReward(lambda a: a.sum(-1) * float("nan"), 3)
    assert _one_hot_rows(plan(flat, torch.zeros(1), s, discrete=True, generator=g)[None])


def test_continuous_cem_finds_the_optimum_within_bounds():
    target = torch.tensor([0.6, -0.3])
    model = ActionReward(lambda a: -(a - target).pow(2).sum(-1), 2)
    s = PetsPlanSettings(**{**SMALL, "iterations": 8, "population": 128, "elites": 12})
    g = torch.Generator().manual_seed(0)
    result = cem(model, torch.zeros(1), s, discrete=False, eval_mode=True, generator=g)
    assert result.action.shape == (2,) and torch.allclose(result.action, target, atol=0.1)
    assert result.mean.shape == (3, 2)
    # Optimum outside the box: the action is clipped to [-1, 1] and pushed to the edge.
    beyond = ActionReward(lambda a: a @ torch.tensor([5.0, -5.0]), 2)
    for eval_mode in (True, False):
        action = plan(beyond, torch.zeros(3, 1), s, discrete=False, eval_mode=eval_mode, generator=g)
        assert action.shape == (3, 2) and action.abs().max() <= 1.0
    assert (plan(beyond, torch.zeros(1), s, discrete=False, generator=g) * torch.tensor([1.0, -1.0]) > 0.8).all()
    # Warm start from a previous plan's mean.
    warm = cem(model, torch.zeros(1), s, discrete=False, warm_mean=result.mean, generator=g)
    assert torch.allclose(warm.action, target, atol=0.1)


def test_plan_settings_validation():
    with pytest.raises(ValueError):
        PetsPlanSettings(population=4, elites=5)
    with pytest.raises(ValueError):
        PetsPlanSettings(propagation="ts2")


# ----------------------------------------------------------------------------- persistence and learning
def test_state_dict_round_trip_gives_identical_predictions():
    torch.manual_seed(0)
    model = ProbabilisticEnsemble(3, 3, members=3, hidden=16, layers=2)
    opt = make_optimizer(model)
    obs, act = torch.rand(32, 3) * 2 - 1, torch.eye(3)[torch.randint(3, (32,))]
    nxt, rew = torch.rand(32, 3), torch.rand(32)
    for _ in range(3):
        model.update(obs, act, nxt, rew, optimizer=opt)
    state = model.state_dict()
    assert {"input_mean", "input_var", "input_count", "max_logvar", "min_logvar"} <= set(state)
    torch.manual_seed(1)
    copy = ProbabilisticEnsemble(3, 3, members=3, hidden=16, layers=2)
    copy.load_state_dict(state)
    for a, b in zip(model(obs, act), copy(obs, act)):
        assert torch.equal(a, b)
    g1, g2 = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
    actions = act[:4][None].expand(5, -1, -1)
    first = propagate(model, obs[:4], actions, 6, generator=g1)
    second = propagate(copy, obs[:4], actions, 6, generator=g2)
    assert torch.equal(first.states, second.states) and torch.equal(first.rewards, second.rewards)


def test_ensemble_fits_a_linear_system():
    # s' = 0.9 s + 0.5 a, r = s: deltas -0.1 s + 0.5 a.
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    model = ProbabilisticEnsemble(1, 1, members=3, hidden=32, layers=2)
    opt = make_optimizer(model, lr=3e-3)
    for _ in range(300):
        s, a = torch.rand(128, 1) * 2 - 1, torch.rand(128, 1) * 2 - 1
        metrics = model.train_step(opt, s, a, 0.9 * s + 0.5 * a, s[:, 0], g)
    s, a = torch.rand(256, 1) * 2 - 1, torch.rand(256, 1) * 2 - 1
    with torch.no_grad():
        mean, _ = model(s, a)
    target = torch.cat((-0.1 * s + 0.5 * a, s), -1)
    assert (mean - target).pow(2).mean().item() < 1e-3
    assert metrics["logvar"].item() < -3  # the variance shrinks on noiseless data


class _HostRead(Exception):
    pass


def test_training_and_planning_never_read_tensors_on_the_host(monkeypatch):
    torch.manual_seed(0)
    model = ProbabilisticEnsemble(3, 3, members=2, hidden=8, layers=1)
    obs, act, nxt, rew = torch.rand(16, 3), torch.eye(3)[torch.randint(3, (16,))], torch.rand(16, 3), torch.rand(16)
    g = torch.Generator().manual_seed(0)

    def refuse(*_, **__):
        raise _HostRead("host read of a tensor")

    for name in ("item", "cpu", "numpy", "tolist", "__bool__", "__float__", "__int__", "__index__"):
        monkeypatch.setattr(torch.Tensor, name, refuse)
    # Adam's CPU step reads its step counter on the host, a CPU artefact: the optimizer is stubbed out.
    stub = SimpleNamespace(zero_grad=lambda set_to_none=True: None, step=lambda: None)
    model.train_step(stub, obs, act, nxt, rew, g)
    s = PetsPlanSettings(**SMALL)
    cem(model, obs[0], s, discrete=True, eval_mode=False, generator=g, state_bounds=(-1.0, 1.0))
    cem(model, obs[:2], s, discrete=False, eval_mode=False, generator=g)
    propagate(model, obs[:2], act[:2][None].expand(3, -1, -1), 3, "ts1", g)  # the unbalanced path too
    with pytest.raises(_HostRead):
        model.update(obs, act, nxt, rew, g, optimizer=stub)  # its floats are the one read


# ----------------------------------------------------------------------------- the agent
def _batch(horizon: int, rows: int, obs_dim: int, act_dim: int) -> SimpleNamespace:
    obs = torch.rand(rows, obs_dim) * 2 - 1
    next_obs = torch.rand(horizon + 1, rows, obs_dim) * 2 - 1
    actions = torch.eye(act_dim)[torch.randint(act_dim, (horizon + 1, rows))]
    return SimpleNamespace(obs=obs, next_obs=next_obs, actions=actions, rewards=torch.rand(horizon + 1, rows))


def test_agent_transitions_chain_the_sequences():
    batch = _batch(2, 4, 3, 3)
    obs, act, nxt, rew = PetsAgent.transitions(batch)
    assert obs.shape == nxt.shape == (12, 3) and act.shape == (12, 3) and rew.shape == (12,)
    assert torch.equal(obs[:4], batch.obs) and torch.equal(obs[4:8], batch.next_obs[0])
    assert torch.equal(nxt[8:], batch.next_obs[2]) and torch.equal(rew[4:8], batch.rewards[1])


def test_grid_agent_acts_updates_and_round_trips():
    torch.manual_seed(0)
    cfg = PetsConfig(members=2, hidden=16, layers=2, plan=PetsPlanSettings(**SMALL))
    agent = PetsAgent(cfg.build_world_model(3, 3), cfg=cfg, discrete=True, generator=torch.Generator().manual_seed(0))
    action = agent.act(np.zeros(3, dtype=np.float32), step=0, eval_mode=False, first_step=True)
    assert action.shape == (3,) and action.sum() == 1 and set(np.unique(action)) <= {0.0, 1.0}
    actions = agent.act(np.zeros((2, 3), dtype=np.float32), step=0, eval_mode=True, first_step=True)
    assert actions.shape == (2, 3) and (actions.sum(-1) == 1).all()
    random = agent.random_action(np.random.default_rng(0))
    assert random.sum() == 1 and random.shape == (3,)
    before = [p.clone() for p in agent.world_model.parameters()]
    metrics = agent.update(_batch(2, 8, 3, 3), step=0, world_model_loss=lambda: agent.world_model.max_logvar.sum() * 0)
    assert torch.equal(metrics.pop("priority"), torch.ones(8))
    assert {"model_nll", "model_mse", "model_logvar", "model_extra_loss"} <= set(metrics)
    assert any(not torch.equal(a, b) for a, b in zip(before, agent.world_model.parameters()))
    assert set(agent.update(_batch(2, 8, 3, 3), step=0, train_world_model=False)) == {"priority"}
    assert agent.state_dict() == {"warm_mean": None}


def test_continuous_agent_keeps_a_warm_start_and_needs_a_reward():
    cfg = PetsConfig(members=2, hidden=8, layers=1, plan=PetsPlanSettings(**SMALL))
    agent = PetsAgent(cfg.build_world_model(2, 2), cfg=cfg, discrete=False)
    action = agent.act(np.zeros(2, dtype=np.float32), step=0, eval_mode=False, first_step=True)
    assert action.shape == (2,) and np.abs(action).max() <= 1.0
    state = agent.state_dict()
    assert state["warm_mean"].shape == (3, 2)
    other = PetsAgent(cfg.build_world_model(2, 2), cfg=cfg, discrete=False)
    other.load_state_dict(state)
    assert torch.equal(other.state_dict()["warm_mean"], state["warm_mean"])
    assert np.abs(agent.act(np.zeros(2, dtype=np.float32), 1, eval_mode=True, first_step=False)).max() <= 1.0
    no_reward = ProbabilisticEnsemble(2, 2, members=2, hidden=4, layers=1, predict_reward=False)
    with pytest.raises(ValueError):
        PetsAgent(no_reward, cfg=cfg, discrete=False)
    known = PetsAgent(no_reward, cfg=cfg, discrete=False, known_reward=lambda s, a, s2: -s2.pow(2).sum(-1))
    assert np.abs(known.act(np.zeros(2, dtype=np.float32), 0, True, True)).max() <= 1.0
