"""Behaviour tests of the TD-MPC agent against the closed forms of paper §2; docs: Design, the agent.

Every network is tiny (mlp_dim 16). The expected values are written out from the paper's formulas (§2, §3)
with explicit loops, never by calling the code under test a second time.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from drago.agent.agent import Agent
from drago.agent.buffer import Batch
from drago.agent.losses import model_losses, policy_loss
from drago.agent.networks import TaskHeads, WorldModel, autocast
from drago.agent.planner import PlanSettings, plan_continuous, plan_discrete, trajectory_returns
from drago.config import AgentConfig
from helpers import tdmpc_config, filled_buffer

OBS, ACT, B, H = 3, 3, 4, 3
RHO, GAMMA = 0.5, 0.99
MLP = 16
# Hand-chosen rewards r_t for t = 0..H (rows) and 4 samples (columns). Row t = H must be ignored by
# every loss (the sequence is H+1 long, only t < H is used), so it holds a conspicuous value.
REWARDS = [
    [1.0, -0.5, 0.0, 2.0],
    [0.5, 1.5, -1.0, 0.25],
    [-2.0, 0.75, 1.0, 0.0],
    [9.0, 9.0, 9.0, 9.0],
]


def make_world(seed: int = 0, act_dim: int = ACT, squash: bool = True, use_crelu: bool = True) -> WorldModel:
    torch.manual_seed(seed)
    return WorldModel(OBS, act_dim, MLP, use_crelu=use_crelu, squash=squash)


def make_heads(seed: int = 1, act_dim: int = ACT, discrete: bool = True) -> TaskHeads:
    torch.manual_seed(seed)
    return TaskHeads(OBS, act_dim, MLP, discrete=discrete)


def make_batch(seed: int = 2, weights: list[float] | None = None) -> Batch:
    g = torch.Generator().manual_seed(seed)
    obs = torch.rand(B, OBS, generator=g) * 2 - 1
    actions = F.one_hot(torch.randint(0, ACT, (H + 1, B), generator=g), ACT).float()
    rewards = torch.tensor(REWARDS)
    next_obs = torch.rand(H + 1, B, OBS, generator=g) * 2 - 1
    w = torch.ones(B) if weights is None else torch.tensor(weights)
    return Batch(obs=obs, actions=actions, rewards=rewards, next_obs=next_obs, weights=w,
                 indices=np.arange(B, dtype=np.int64))


def losses_for(wm, heads, batch, **kw):
    c = AgentConfig().tdmpc
    args = dict(horizon=H, rho=RHO, discount=GAMMA, policy_std=0.05, consistency_coef=c.consistency_coef,
                reward_coef=c.reward_coef, value_coef=c.value_coef, first_step_qr_only=False,
                train_world_model=True)
    args.update(kw)
    return model_losses(wm, heads, batch.obs, batch.actions, batch.rewards, batch.next_obs, **args)


def reference_rollout(wm: WorldModel, batch: Batch) -> list[torch.Tensor]:
    """z_0 = s_0, z_{t+1} = d(z_t, a_t): the model's open-loop rollout, t = 0..H."""
    with torch.no_grad():
        z = batch.obs.clone()
        out = [z]
        for t in range(H):
            z = wm(z, batch.actions[t])
            out.append(z)
    return out


def perturb_last_layers(heads: TaskHeads, seed: int = 5) -> None:
    """Give the reward head and the online critics a non-zero last layer (they start at exactly 0)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        heads.reward[-1].weight.copy_(torch.randn(heads.reward[-1].weight.shape, generator=g) * 0.5)
        heads.reward[-1].bias.fill_(0.1)
        heads.q.l3.weight.copy_(torch.randn(heads.q.l3.weight.shape, generator=g) * 0.5)


def set_target_q_constant(heads: TaskHeads, c1: float, c2: float) -> None:
    """Target critics that output the constants c1, c2 whatever the input (zero weights, set biases)."""
    with torch.no_grad():
        heads.q_target.l3.weight.zero_()
        heads.q_target.l3.bias[0].fill_(c1)
        heads.q_target.l3.bias[1].fill_(c2)


def params(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b))


# ---------------------------------------------------------------------------------------------------
# 1. Closed forms of the losses (paper §2; docs: Design, the agent zero last layers, paper §2; docs: Design, the agent)
# ---------------------------------------------------------------------------------------------------
def test_loss_coefficients_are_the_spec_defaults():
    c = AgentConfig().tdmpc
    assert (c.consistency_coef, c.reward_coef, c.value_coef, c.rho, c.discount) == (2.0, 0.5, 0.1, 0.5, 0.99)


def test_reward_value_heads_start_at_zero():
    heads = make_heads()
    z = torch.randn(7, OBS)
    a = F.one_hot(torch.randint(0, ACT, (7,)), ACT).float()
    assert torch.equal(heads.predict_reward(z, a), torch.zeros(7))
    assert torch.equal(heads.q_values(z, a), torch.zeros(2, 7))
    assert torch.equal(heads.q_values(z, a, target=True), torch.zeros(2, 7))


def test_reward_and_value_loss_closed_form_at_init():
    wm, heads, batch = make_world(), make_heads(), make_batch()
    out = losses_for(wm, heads, batch)
    for i in range(B):
        r = [REWARDS[t][i] for t in range(H)]
        expected_reward = sum(RHO ** t * r[t] ** 2 for t in range(H))
        expected_value = sum(RHO ** t * 2 * r[t] ** 2 for t in range(H))  # TD target = r_t, Q = 0, two critics
        assert out.reward[i].item() == pytest.approx(expected_reward, rel=1e-6, abs=1e-7)
        assert out.value[i].item() == pytest.approx(expected_value, rel=1e-6, abs=1e-7)


def test_first_step_qr_only_keeps_only_t0():
    wm, heads, batch = make_world(), make_heads(), make_batch()
    out = losses_for(wm, heads, batch, first_step_qr_only=True)
    for i in range(B):
        r0 = REWARDS[0][i]
        assert out.reward[i].item() == pytest.approx(r0 ** 2, abs=1e-7)
        assert out.value[i].item() == pytest.approx(2 * r0 ** 2, abs=1e-7)
        # The priority still sums over every step of the sequence.
        expected_priority = sum(RHO ** t * 2 * abs(REWARDS[t][i]) for t in range(H))
        assert out.priority[i].item() == pytest.approx(expected_priority, rel=1e-6)


def test_consistency_total_and_prediction_score_closed_form():
    wm, heads, batch = make_world(), make_heads(), make_batch()
    out = losses_for(wm, heads, batch)
    z = reference_rollout(wm, batch)
    mse = [((z[t + 1] - batch.next_obs[t]) ** 2).mean(-1) for t in range(H)]  # (B,) each
    expected_c = sum(RHO ** t * mse[t] for t in range(H))
    torch.testing.assert_close(out.consistency.detach(), expected_c, rtol=1e-5, atol=1e-7)
    assert out.consistency.min() > 0  # a real rollout, not a zero
    expected_total = 2.0 * expected_c + 0.5 * out.reward.detach() + 0.1 * out.value.detach()
    torch.testing.assert_close(out.total.detach(), expected_total, rtol=1e-5, atol=1e-7)
    expected_score = sum(-torch.log(mse[t]) for t in range(H)).mean() / H
    assert out.prediction_score.item() == pytest.approx(expected_score.item(), rel=1e-5)
    # The stored latents are z_0 (real) and the model's predictions z_1..z_H.
    torch.testing.assert_close(out.latents, torch.stack(z), rtol=1e-6, atol=1e-7)


def test_no_world_model_training_gives_zero_consistency_and_score():
    wm, heads, batch = make_world(), make_heads(), make_batch()
    out = losses_for(wm, heads, batch, train_world_model=False)
    assert torch.equal(out.consistency, torch.zeros(B))
    assert out.prediction_score.item() == 0.0
    # Reward and value terms are unaffected.
    ref = losses_for(wm, heads, batch)
    torch.testing.assert_close(out.reward, ref.reward.detach())
    torch.testing.assert_close(out.value, ref.value.detach())
    torch.testing.assert_close(out.latents, ref.latents)


def test_heads_are_fitted_on_imagined_latents_with_real_targets():
    """With non-zero heads: L_r and L_v use z_t of the model rollout, targets r_t and r_t + gamma min Q-."""
    wm, heads, batch = make_world(), make_heads(), make_batch()
    perturb_last_layers(heads)
    c1, c2 = 0.7, -0.3
    set_target_q_constant(heads, c1, c2)
    out = losses_for(wm, heads, batch)
    z = reference_rollout(wm, batch)
    with torch.no_grad():
        exp_r = torch.zeros(B)
        exp_v = torch.zeros(B)
        exp_p = torch.zeros(B)
        for t in range(H):
            r = batch.rewards[t]
            delta = r + GAMMA * min(c1, c2)
            rhat = heads.predict_reward(z[t], batch.actions[t])
            q = heads.q_values(z[t], batch.actions[t])
            exp_r += RHO ** t * (rhat - r) ** 2
            exp_v += RHO ** t * ((q[0] - delta) ** 2 + (q[1] - delta) ** 2)
            exp_p += RHO ** t * ((q[0] - delta).abs() + (q[1] - delta).abs())
    torch.testing.assert_close(out.reward.detach(), exp_r, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out.value.detach(), exp_v, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out.priority, exp_p, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------------
# 2. Priorities
# ---------------------------------------------------------------------------------------------------
def test_learner_and_reviewer_priorities_at_init():
    wm, heads, batch = make_world(), make_heads(), make_batch()
    learner = losses_for(wm, heads, batch)
    reviewer = losses_for(wm, heads, batch, reviewer_priority=True)
    for i in range(B):
        lp = sum(RHO ** t * 2 * abs(REWARDS[t][i]) for t in range(H))
        rp = sum(RHO ** t * (2 * abs(REWARDS[t][i]) + REWARDS[t][i] + 2) for t in range(H))
        assert learner.priority[i].item() == pytest.approx(lp, rel=1e-6)
        assert reviewer.priority[i].item() == pytest.approx(rp, rel=1e-6)


def test_agent_update_reports_priorities_and_weighted_loss():
    cfg = tdmpc_config(mlp_dim=MLP, horizon=H, batch_size=B)
    for reviewer in (False, True):
        wm = make_world()
        agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters(), lr=cfg.lr), cfg, discrete=True,
                      reviewer=reviewer)
        batch = make_batch(weights=[1.0, 0.5, 0.25, 0.8])
        torch.manual_seed(3)
        metrics = agent.update(batch, step=1)
        for i in range(B):
            p = sum(RHO ** t * (2 * abs(REWARDS[t][i]) + (REWARDS[t][i] + 2 if reviewer else 0)) for t in range(H))
            assert metrics["priority"][i].item() == pytest.approx(p, rel=1e-6)
        # Weighted mean with the PER weights, scaled by 1/H (paper §2; docs: Design, the agent step 4).
        wm2, heads2 = make_world(), make_heads()
        ref = losses_for(wm2, heads2, batch)
        expected = (batch.weights * ref.total.detach()).mean().item() / H
        assert metrics["weighted_loss"].item() == pytest.approx(expected, rel=1e-5)


# ---------------------------------------------------------------------------------------------------
# 3. Gradient isolation (paper §2; docs: Design, the agent summary)
# ---------------------------------------------------------------------------------------------------
def _grads(loss: torch.Tensor, module: torch.nn.Module) -> list[torch.Tensor]:
    ps = [p for p in module.parameters() if p.requires_grad]
    gs = torch.autograd.grad(loss, ps, allow_unused=True, retain_graph=True)
    return [torch.zeros_like(p) if g is None else g for p, g in zip(ps, gs)]


def _norm(gs: list[torch.Tensor]) -> float:
    return float(sum(g.pow(2).sum() for g in gs)) ** 0.5


def test_gradient_isolation_between_world_model_and_heads():
    wm, heads, batch = make_world(), make_heads(), make_batch()
    perturb_last_layers(heads)  # otherwise zero last layers would hide any leak
    out = losses_for(wm, heads, batch)
    # The reward and value losses train their heads but never the dynamics.
    assert _norm(_grads(out.reward.sum(), heads.reward)) > 0
    assert _norm(_grads(out.reward.sum(), wm)) == 0.0
    assert _norm(_grads(out.value.sum(), heads.q)) > 0
    assert _norm(_grads(out.value.sum(), wm)) == 0.0
    # The consistency loss trains the dynamics and nothing of the heads.
    assert _norm(_grads(out.consistency.sum(), wm.dynamics)) > 0
    assert _norm(_grads(out.consistency.sum(), heads)) == 0.0
    # The model loss never reaches the policy.
    assert _norm(_grads(out.total.sum(), heads.policy)) == 0.0


def test_policy_loss_closed_form_uses_all_h_plus_one_latents():
    heads = make_heads()
    with torch.no_grad():
        heads.q.l3.weight.zero_()
        heads.q.l3.bias[0].fill_(0.4)
        heads.q.l3.bias[1].fill_(1.5)
    latents = torch.rand(H + 1, B, OBS)
    loss = policy_loss(heads, latents, RHO, 0.05)
    expected = -sum(RHO ** t * 0.4 for t in range(H + 1))
    assert loss.item() == pytest.approx(expected, rel=1e-6)


def test_policy_step_does_not_move_critics_or_reward():
    """With the model and world optimizers at lr 0, an update may change the policy and nothing else."""
    cfg = tdmpc_config(mlp_dim=MLP, horizon=H, batch_size=B)
    wm = make_world()
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters(), lr=cfg.lr), cfg, discrete=True)
    perturb_last_layers(agent.heads)  # non-zero critics: the policy loss has a gradient
    for opt in (agent.model_optimizer, agent.world_optimizer):
        for group in opt.param_groups:
            group["lr"] = 0.0
    batch = make_batch()
    out = losses_for(wm, agent.heads, batch)
    pi = policy_loss(agent.heads, out.latents, RHO, cfg.tdmpc.min_std)
    assert _norm(_grads(pi, agent.heads.q)) > 0  # the policy loss does reach Q: it must be kept out
    q0, r0, p0, d0 = params(agent.heads.q), params(agent.heads.reward), params(agent.heads.policy), params(wm)
    torch.manual_seed(4)
    agent.update(batch, step=1)  # 1 % update_freq != 0: no EMA either
    assert same(q0, params(agent.heads.q))
    assert same(r0, params(agent.heads.reward))
    assert same(d0, params(wm))
    assert not same(p0, params(agent.heads.policy))


# ---------------------------------------------------------------------------------------------------
# 4. Which parameters an update moves; target EMA
# ---------------------------------------------------------------------------------------------------
def _agent_with_offset_targets(tau: float = 0.25, update_freq: int = 3) -> Agent:
    cfg = tdmpc_config(mlp_dim=MLP, horizon=H, batch_size=B, tau=tau, update_freq=update_freq)
    wm = make_world()
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters(), lr=cfg.lr), cfg, discrete=True)
    # Targets that differ from the online nets, so an EMA (or its absence) is visible.
    with torch.no_grad():
        for p in [*agent.heads.q_target.parameters(), *wm.target.parameters()]:
            p.add_(0.1 * torch.randn_like(p))
    return agent


def test_update_without_world_model_training_leaves_world_model_alone():
    agent = _agent_with_offset_targets()
    wm = agent.world_model
    dyn, tgt = params(wm.dynamics), params(wm.target)
    q0 = params(agent.heads.q)
    agent.update(make_batch(), step=0, train_world_model=False)  # step 0: an EMA step for the heads
    assert same(dyn, params(wm.dynamics))
    assert same(tgt, params(wm.target))
    assert not same(q0, params(agent.heads.q))  # the heads did learn


def test_update_with_world_model_training_moves_dynamics_and_its_target():
    agent = _agent_with_offset_targets(tau=0.25)
    wm = agent.world_model
    dyn, tgt = params(wm.dynamics), params(wm.target)
    agent.update(make_batch(), step=0, train_world_model=True)
    new_dyn = params(wm.dynamics)
    assert not same(dyn, new_dyn)
    for old, online, now in zip(tgt, new_dyn, params(wm.target)):
        torch.testing.assert_close(now, 0.75 * old + 0.25 * online, rtol=1e-5, atol=1e-6)


def test_heads_ema_update_closed_form():
    heads = make_heads()
    perturb_last_layers(heads)
    with torch.no_grad():
        for p in heads.q_target.parameters():
            p.add_(torch.randn_like(p))
    old, online = params(heads.q_target), params(heads.q)
    heads.ema_update(0.3)
    for o, q, n in zip(old, online, params(heads.q_target)):
        torch.testing.assert_close(n, 0.7 * o + 0.3 * q, rtol=1e-5, atol=1e-6)
    assert same(online, params(heads.q))


def test_agent_update_applies_ema_only_every_update_freq_steps():
    agent = _agent_with_offset_targets(tau=0.25, update_freq=3)
    batch = make_batch()
    for step in (1, 2, 4, 5):
        before = params(agent.heads.q_target)
        agent.update(batch, step=step)
        assert same(before, params(agent.heads.q_target)), f"EMA applied at step {step}"
    before = params(agent.heads.q_target)
    agent.update(batch, step=6)
    online = params(agent.heads.q)
    for o, q, n in zip(before, online, params(agent.heads.q_target)):
        torch.testing.assert_close(n, 0.75 * o + 0.25 * q, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------------
# 5. Policy sampling (paper §2; docs: Design, the agent)
# ---------------------------------------------------------------------------------------------------
def test_grid_policy_returns_exact_one_hots():
    heads = make_heads()
    z = torch.rand(200, OBS) * 2 - 1
    torch.manual_seed(0)
    for deterministic in (False, True):
        a = heads.act(z, 0.05, deterministic=deterministic)
        assert a.shape == (200, ACT)
        assert torch.all((a == 0) | (a == 1))
        assert torch.equal(a.sum(-1), torch.ones(200))
    greedy = heads.act(z, 0.05, deterministic=True)
    assert torch.equal(greedy.argmax(-1), heads.policy(z).argmax(-1))
    sampled = heads.act(z, 0.05)
    assert not torch.equal(sampled, greedy)  # Gumbel noise in training mode


def test_continuous_policy_bounds_and_noise_clip():
    heads = make_heads(act_dim=2, discrete=False)
    with torch.no_grad():
        heads.policy[-1].weight.mul_(20.0)  # push some tanh(mu) into saturation
    torch.manual_seed(0)
    z = torch.rand(2000, OBS) * 2 - 1
    with torch.no_grad():
        mu = torch.tanh(heads.policy(z))
        assert torch.equal(heads.act(z, 0.5, deterministic=True), mu)
        for std in (0.05, 5.0):
            a = heads.act(z, std)
            assert a.min().item() >= -1 + 1e-6 - 1e-7 and a.max().item() <= 1 - 1e-6 + 1e-7
            assert ((a - mu).abs() <= 0.3 + 1e-6).all()
            interior = mu.abs() < 0.6
            assert interior.sum() > 100
            noise = (a - mu)[interior]
            if std == 5.0:
                # Almost every draw of N(0, 25) is clipped to exactly +-0.3.
                assert ((noise.abs() - 0.3).abs() < 1e-5).float().mean() > 0.9
            else:
                assert noise.std().item() == pytest.approx(0.05, rel=0.15)
        assert ((a.abs() - (1 - 1e-6)).abs() < 1e-6).any()  # the clamp was exercised


# ---------------------------------------------------------------------------------------------------
# 6. Planner (paper §2; docs: Design, the agent)
# ---------------------------------------------------------------------------------------------------
def settings(**kw) -> PlanSettings:
    base = dict(horizon=3, iterations=4, num_samples=64, num_elites=8, num_policy_trajectories=4,
                temperature=0.5, momentum=0.1, discount=GAMMA, use_q=False, policy_std=0.05, min_std=0.05,
                max_std=2.0, elite_selection="argmax")
    base.update(kw)
    return PlanSettings(**base)


def test_plan_discrete_returns_a_one_hot():
    wm, heads = make_world(), make_heads()
    torch.manual_seed(0)
    for eval_mode in (False, True):
        a = plan_discrete(wm, heads, torch.tensor([0.1, -0.2, 0.3]), settings(use_q=True, elite_selection="sample"),
                          eval_mode)
        assert a.shape == (ACT,)
        assert torch.all((a == 0) | (a == 1)) and a.sum().item() == 1.0


@pytest.mark.parametrize("paid", [0, 1, 2])
@pytest.mark.parametrize("variant", ["cem", "one-shot-argmax"])
def test_plan_discrete_picks_the_only_rewarded_action(monkeypatch, paid, variant):
    """CEM converges on the paid action; with one iteration and every sample an elite, "argmax" must
    still return the best sequence's first action (the worst one would almost surely differ)."""
    wm, heads = make_world(), make_heads()
    monkeypatch.setattr(heads, "predict_reward", lambda z, a: a[..., paid])
    s = settings() if variant == "cem" else settings(iterations=1, num_samples=64, num_elites=64,
                                                         num_policy_trajectories=0)
    torch.manual_seed(paid)
    for eval_mode in (False, True):
        for obs in (torch.tensor([0.5, 0.5, 0.0]), torch.tensor([-0.9, 0.1, 1.0])):
            a = plan_discrete(wm, heads, obs, s, eval_mode)
            assert a.argmax().item() == paid


def test_plan_continuous_shapes_bounds_and_optimum(monkeypatch):
    wm, heads = make_world(act_dim=2, squash=False, use_crelu=False), make_heads(act_dim=2, discrete=False)
    monkeypatch.setattr(heads, "predict_reward", lambda z, a: -((a - 0.5) ** 2).sum(-1))
    torch.manual_seed(0)
    s = settings(iterations=6, num_samples=256, num_elites=32, num_policy_trajectories=0)
    obs = torch.tensor([0.2, 0.1, -0.3])
    action, mean = plan_continuous(wm, heads, obs, s, eval_mode=True, warm_mean=None)
    assert action.shape == (2,) and mean.shape == (3, 2)
    assert torch.all(action.abs() <= 1)
    assert torch.allclose(action, torch.full((2,), 0.5), atol=0.15)
    # Warm start from the returned mean, with policy trajectories mixed in.
    action2, mean2 = plan_continuous(wm, heads, obs, settings(num_policy_trajectories=4), eval_mode=True,
                                     warm_mean=mean)
    assert action2.shape == (2,) and mean2.shape == (3, 2)


def test_plan_continuous_training_action_stays_in_bounds(monkeypatch):
    wm, heads = make_world(act_dim=2, squash=False, use_crelu=False), make_heads(act_dim=2, discrete=False)
    monkeypatch.setattr(heads, "predict_reward", lambda z, a: a.sum(-1))  # pushes towards +1
    torch.manual_seed(0)
    actions = [plan_continuous(wm, heads, torch.zeros(3), settings(max_std=2.0, min_std=1.0), eval_mode=False,
                               warm_mean=None)[0] for _ in range(20)]
    stacked = torch.stack(actions)
    assert stacked.min() >= -1 and stacked.max() <= 1
    assert (stacked == 1).any()  # exploration noise pushed past the bound and was clipped


def test_batched_planning_solves_each_problem_and_one_problem_is_unbatched(monkeypatch):
    """E observations planned as one batch: each gets its own optimum; a batch of one draws and computes
    exactly what a single observation does (training plans one observation at a time)."""
    wm, heads = make_world(), make_heads()
    monkeypatch.setattr(wm, "forward", lambda z, a: z)  # the latent never moves: a_t . z_0 pays at every step
    monkeypatch.setattr(heads, "predict_reward", lambda z, a: (a * z).sum(-1))
    obs = torch.eye(OBS)  # observation k pays action k
    torch.manual_seed(0)
    actions = plan_discrete(wm, heads, obs, settings(), eval_mode=True)
    assert torch.equal(actions, torch.eye(ACT))

    wm2, heads2 = make_world(act_dim=2, squash=False, use_crelu=False), make_heads(act_dim=2, discrete=False)
    targets = torch.tensor([[0.5, -0.5], [-0.6, 0.2], [0.1, 0.7]])
    monkeypatch.setattr(heads2, "predict_reward", lambda z, a: -((a - z[..., :2]) ** 2).sum(-1))
    monkeypatch.setattr(wm2, "forward", lambda z, a: z)
    obs2 = torch.cat((targets, torch.zeros(3, 1)), dim=1)
    s = settings(iterations=6, num_samples=256, num_elites=32, num_policy_trajectories=0)
    action, mean = plan_continuous(wm2, heads2, obs2, s, eval_mode=True, warm_mean=None)
    assert action.shape == (3, 2) and mean.shape == (3, 3, 2)
    torch.testing.assert_close(action, targets, atol=0.15, rtol=0)
    action, mean = plan_continuous(wm2, heads2, obs2, s, eval_mode=False, warm_mean=mean)  # warm-started
    assert action.shape == (3, 2) and torch.all(action.abs() <= 1)

    wm3, heads3 = make_world(), make_heads()
    for selection in ("sample", "argmax"):
        s = settings(use_q=True, elite_selection=selection)
        single, batch = [], []
        for out, x in ((single, obs[1]), (batch, obs[1:2])):
            torch.manual_seed(3)
            out.append(plan_discrete(wm3, heads3, x, s, eval_mode=False))
            out.append(plan_continuous(wm2, heads2, obs2[1] if x.dim() == 1 else obs2[1:2], s, eval_mode=False,
                                       warm_mean=None))
            out.append(torch.rand(4))  # the generator moved by the same draws
        assert torch.equal(single[0], batch[0][0]) and torch.equal(single[1][0], batch[1][0][0])
        assert torch.equal(single[1][1], batch[1][1][:, 0]) and torch.equal(single[2], batch[2])
    with pytest.raises(ValueError, match=r"shape \(n,\) or \(E, n\)"):
        plan_discrete(wm, heads, torch.zeros(1, 2, OBS), settings(), eval_mode=True)


def test_trajectory_returns_closed_form_and_reward_bonus(monkeypatch):
    wm, heads = make_world(act_dim=2, squash=False, use_crelu=False), make_heads(act_dim=2, discrete=False)
    monkeypatch.setattr(heads, "predict_reward", lambda z, a: a.sum(-1))
    g = torch.Generator().manual_seed(7)
    h, n = 4, 6
    actions = torch.rand(h, n, 2, generator=g) * 2 - 1  # mixed signs
    z0 = torch.tensor([0.3, -0.2, 0.5])

    # Reference: explicit loop over the model's rollout.
    zs = [z0.expand(n, -1)]
    for t in range(h):
        zs.append(wm(zs[-1], actions[t]).detach())
    r = [actions[t].sum(-1) for t in range(h)]
    expected = sum(GAMMA ** t * r[t] for t in range(h))
    got = trajectory_returns(wm, heads, z0, actions, GAMMA, use_q=False, policy_std=0.05)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    assert (torch.stack(r) < 0).any() and (torch.stack(r) >= 0).any()

    # Bonus of the predicted next state z_{t+1}, on non-negative rewards only.
    def bonus(z):
        return 2.0 + z.abs().sum(-1)

    expected_b = sum(GAMMA ** t * torch.where(r[t] >= 0, r[t] * bonus(zs[t + 1]), r[t]) for t in range(h))
    got_b = trajectory_returns(wm, heads, z0, actions, GAMMA, use_q=False, policy_std=0.05, bonus=bonus)
    torch.testing.assert_close(got_b, expected_b, rtol=1e-5, atol=1e-6)

    # Terminal value gamma^h min(Q1, Q2) when use_q.
    with torch.no_grad():
        heads.q.l3.weight.zero_()
        heads.q.l3.bias[0].fill_(3.0)
        heads.q.l3.bias[1].fill_(-1.0)
    got_q = trajectory_returns(wm, heads, z0, actions, GAMMA, use_q=True, policy_std=0.05)
    torch.testing.assert_close(got_q, expected + GAMMA ** h * -1.0, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------------
# 7-8. Horizon schedule and seed-phase actions
# ---------------------------------------------------------------------------------------------------
def test_planning_horizon_schedule():
    cfg = tdmpc_config(mlp_dim=MLP, horizon=10, horizon_schedule_steps=1000)
    wm = make_world()
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters()), cfg, discrete=True)
    assert agent.planning_horizon(0) == 1
    assert agent.planning_horizon(500) == 5  # int(1 + 0.5 * 9)
    assert agent.planning_horizon(1000) == 10
    assert agent.planning_horizon(50_000) == 10
    assert agent.plan_settings(0).horizon == 1
    assert AgentConfig().tdmpc.horizon_schedule_steps == 10_000 and AgentConfig().tdmpc.horizon == 10


def test_random_grid_action_frequencies():
    wm = make_world()
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters()), tdmpc_config(mlp_dim=MLP), discrete=True)
    rng = np.random.default_rng(0)
    draws = np.stack([agent.random_action(rng) for _ in range(6000)])
    assert draws.shape == (6000, 3)
    assert set(np.unique(draws)) <= {0.0, 1.0}
    assert np.all(draws.sum(1) == 1)
    np.testing.assert_allclose(draws.mean(0), [0.2, 0.2, 0.6], atol=0.025)


def test_random_continuous_action_is_uniform_in_box():
    torch.manual_seed(0)
    wm = WorldModel(OBS, 2, MLP, use_crelu=False, squash=False)
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters()), tdmpc_config(mlp_dim=MLP), discrete=False)
    rng = np.random.default_rng(0)
    draws = np.stack([agent.random_action(rng) for _ in range(2000)])
    assert draws.shape == (2000, 2) and draws.min() >= -1 and draws.max() <= 1
    assert math.isclose(float(draws.mean()), 0.0, abs_tol=0.05)


# ---------------------------------------------------------------------------------------------------
# 9. Speed: shared rollouts, reduced precision, device-resident priorities, torch.compile
# ---------------------------------------------------------------------------------------------------
def _twin_agents(reviewer: bool = False) -> tuple[Agent, Agent]:
    """Two identical agents (same world model weights, same heads), each with its own world model."""
    cfg = tdmpc_config(mlp_dim=MLP, horizon=H, batch_size=B)
    out = []
    for _ in range(2):
        wm = make_world()
        agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters(), lr=cfg.lr), cfg, discrete=True,
                      reviewer=reviewer)
        torch.manual_seed(11)
        agent.heads.load_state_dict(make_heads().state_dict())
        perturb_last_layers(agent.heads)
        out.append(agent)
    return out[0], out[1]


@pytest.mark.parametrize("train_world_model", [False, True])
def test_update_from_a_given_rollout_equals_its_own(train_world_model):
    """DRAGO hands each update its rows of one shared rollout; the update must not change for it."""
    own, shared = _twin_agents(reviewer=train_world_model)
    batch, other = make_batch(seed=2), make_batch(seed=9)
    both = other.concat(batch)
    torch.manual_seed(5)
    ref = own.update(batch, step=0, train_world_model=train_world_model)
    latents = shared.rollout(both.obs, both.actions)[:, B:]
    torch.manual_seed(5)
    got = shared.update(batch, step=0, train_world_model=train_world_model,
                        latents=latents if train_world_model else latents.detach())
    for key in ref:
        torch.testing.assert_close(got[key], ref[key], rtol=1e-5, atol=1e-6)
    for a, b in zip(params(own.heads), params(shared.heads)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    for a, b in zip(params(own.world_model), params(shared.world_model)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="do not match"):
        shared.update(batch, step=1, train_world_model=False, latents=latents[:-1].detach())


def test_output_layers_stay_float32_under_bfloat16_autocast():
    wm, heads = make_world(), make_heads()
    perturb_last_layers(heads)
    z, a = torch.rand(64, OBS) * 2 - 1, F.one_hot(torch.randint(0, ACT, (64,)), ACT).float()
    with torch.no_grad():
        full = (wm(z, a), heads.predict_reward(z, a), heads.q_values(z, a), heads.policy(z))
        with autocast("cpu", "bfloat16"):
            low = (wm(z, a), heads.predict_reward(z, a), heads.q_values(z, a), heads.policy(z))
            hidden = heads.reward[0](torch.cat((z, a), -1))
    assert hidden.dtype == torch.bfloat16  # the hidden layers do run in bfloat16 ...
    for f, x in zip(full, low):
        assert x.dtype == torch.float32  # ... but every output is float32
        assert not torch.equal(f, x) and torch.allclose(f, x, rtol=0.05, atol=0.05)
    with autocast("cpu", "float32"):
        assert torch.equal(wm(z, a), full[0])
    with pytest.raises(ValueError, match="valid: float32, bfloat16"):
        autocast("cpu", "float16")


def test_precision_setting_is_validated():
    from drago.config import ConfigError, load_config

    assert load_config("smoke").agent.tdmpc.precision == "auto"  # a run resolves it (tests/test_speed.py)
    assert load_config("smoke", ["agent.tdmpc.precision=bfloat16"]).agent.tdmpc.precision == "bfloat16"
    with pytest.raises(ConfigError, match="unknown agent.tdmpc.precision 'float16'; valid choices: auto, float32, bfloat16"):
        load_config("smoke", ["agent.tdmpc.precision=float16"])


def _fit(precision: str, steps: int = 250, fast_tanh: bool = False) -> dict[str, float]:
    """Fit one agent to a fixed batch whose rewards and values sit near 300 (the grid's Q scale) and vary
    by a few units: in bfloat16 those outputs would be rounded to multiples of 2."""
    torch.manual_seed(0)
    cfg = tdmpc_config(mlp_dim=64, horizon=H, batch_size=64, discount=0.0, update_freq=1, precision=precision,
                      fast_tanh=fast_tanh)
    wm = WorldModel(OBS, ACT, 64, use_crelu=True, squash=True)
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters(), lr=cfg.lr), cfg, discrete=True)
    with torch.no_grad():
        for p in (agent.heads.reward[-1].bias, agent.heads.q.l3.bias, agent.heads.q_target.l3.bias):
            p.fill_(300.0)
    g = torch.Generator().manual_seed(1)
    n = 64
    obs = torch.rand(n, OBS, generator=g) * 2 - 1
    actions = F.one_hot(torch.randint(0, ACT, (H + 1, n), generator=g), ACT).float()
    next_obs = torch.tanh(torch.rand(H + 1, n, OBS, generator=g) * 2 - 1)
    states = torch.cat((obs[None], next_obs[:-1]))
    rewards = 300 + 2 * (states @ torch.tensor([1.0, -0.5, 0.25]) + actions @ torch.tensor([0.5, -1.0, 0.0]))
    batch = Batch(obs, actions, rewards, next_obs, torch.ones(n), np.arange(n))
    for i in range(steps):
        out = agent.update(batch, i)
    return {k: float(out[k]) for k in ("reward_loss", "value_loss", "consistency_loss", "pi_loss")}


@pytest.mark.slow
def test_bfloat16_learns_like_float32(monkeypatch):
    from drago.agent import networks

    full, low = _fit("float32"), _fit("bfloat16")
    for key in ("reward_loss", "value_loss", "consistency_loss"):
        assert low[key] == pytest.approx(full[key], rel=0.25), key
    # The check has teeth: with the output layers left in bfloat16, the reward and value losses stall
    # at the rounding error of outputs near 300.
    monkeypatch.setattr(networks, "_float32_output", lambda x, layer: layer(x))
    broken = _fit("bfloat16")
    assert broken["reward_loss"] > 2 * full["reward_loss"]
    assert broken["value_loss"] > 2 * full["value_loss"]


def test_fast_tanh_matches_tanh_and_its_gradient():
    from drago.agent.networks import tanh

    x = torch.linspace(-20, 20, 400_001, requires_grad=True)  # steps of 1e-4, saturated ends included
    exact, fast = torch.tanh(x), tanh(x, fast=True)
    torch.testing.assert_close(fast, exact, rtol=0, atol=3e-7)
    assert fast[0].item() == -1.0 and fast[-1].item() == 1.0
    g = torch.randn(x.shape, generator=torch.Generator().manual_seed(0))
    (grad_exact,) = torch.autograd.grad(exact, x, g)
    (grad_fast,) = torch.autograd.grad(fast, x, g)
    torch.testing.assert_close(grad_fast, grad_exact, rtol=0, atol=2e-6)
    with torch.no_grad():  # planning takes the path without autograd: the same values
        assert torch.equal(tanh(x, fast=True), fast.detach())
    assert torch.equal(tanh(x, fast=False), exact)


@pytest.mark.slow
def test_fast_tanh_reaches_the_heads_and_learns_like_tanh():
    from drago.config import load_config

    assert load_config("smoke").agent.tdmpc.fast_tanh is True  # the default; false gives torch.tanh's own bits
    assert load_config("smoke", ["agent.tdmpc.fast_tanh=false"]).agent.tdmpc.fast_tanh is False
    wm = make_world()
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters()), tdmpc_config(mlp_dim=MLP, fast_tanh=True),
                  discrete=False)
    exact = make_heads(discrete=False)
    exact.load_state_dict(agent.heads.state_dict())
    perturb_last_layers(exact)
    agent.heads.load_state_dict(exact.state_dict())
    z, a = torch.rand(64, OBS) * 2 - 1, torch.rand(64, ACT) * 2 - 1
    with torch.no_grad():
        q_fast, q_exact = agent.heads.q_values(z, a), exact.q_values(z, a)
        mu_fast, mu_exact = agent.heads.act(z, 0.0), exact.act(z, 0.0)
    assert not torch.equal(q_fast, q_exact)  # the heads do take the sigmoid form ...
    torch.testing.assert_close(q_fast, q_exact, rtol=1e-5, atol=1e-5)  # ... which agrees with tanh
    torch.testing.assert_close(mu_fast, mu_exact, rtol=0, atol=3e-7)
    full, fast = _fit("float32"), _fit("float32", fast_tanh=True)
    for key in ("reward_loss", "value_loss", "consistency_loss"):
        assert fast[key] == pytest.approx(full[key], rel=0.05), key


class _HostRead(AssertionError):
    pass


@pytest.fixture
def no_host_reads(monkeypatch):
    """Fail on any Python-level read of a tensor's value on the host (a sync on a GPU)."""
    def refuse(*_, **__):
        raise _HostRead("host read of a tensor in the hot path")

    for name in ("item", "cpu", "numpy", "tolist", "__bool__", "__float__", "__int__", "__index__"):
        monkeypatch.setattr(torch.Tensor, name, refuse)


def test_hot_path_never_reads_tensors_on_the_host(no_host_reads):
    buf = filled_buffer(device_priorities=True, obs_dim=OBS, act_dim=ACT, horizon=H)
    rng = np.random.default_rng(0)
    wm, heads = make_world(), make_heads()
    continuous_wm, continuous_heads = make_world(act_dim=2, squash=False), make_heads(act_dim=2, discrete=False)
    for _ in range(2):
        batch = buf.sample(B, rng)
        out = losses_for(wm, heads, batch)
        pi = policy_loss(heads, out.latents, RHO, 0.05)
        (out.total.mean() + pi).backward()
        buf.update_priorities(batch.indices, out.priority)
        for selection in ("sample", "argmax"):
            obs = torch.tensor([0.1, -0.2, 0.3])
            plan_discrete(wm, heads, obs, settings(use_q=True, elite_selection=selection), eval_mode=False)
            plan_continuous(continuous_wm, continuous_heads, obs, settings(use_q=True, elite_selection=selection),
                            eval_mode=False, warm_mean=None)
    with pytest.raises(_HostRead):
        torch.ones(1).item()  # the guard is armed


@pytest.mark.experiment
def test_compiled_agent_trains_on_the_smoke_preset(tmp_path):
    """agent.tdmpc.compile=true: torch.compile of the losses and the planner step (over a minute on a CPU)."""
    import csv

    from drago import cli

    out = tmp_path / "run"
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(out), "--no-progress",
                     "train.tensorboard=false", "env.tasks=[room1,room2]", "agent.tdmpc.compile=true",
                     "train.eval_episodes=3"]) == 0  # evaluation plans 3 observations at once
    rows = [r for r in csv.DictReader((out / "train.csv").open()) if r["reviewer_value_loss"]]
    assert rows
    for r in rows:
        for key in ("learner_value_loss", "reviewer_consistency_loss", "reviewer_value_loss", "vae_loss",
                    "rehearsal_loss"):
            assert math.isfinite(float(r[key])), key


@pytest.mark.parametrize("lr_final, step, expected_lr", [
    (None, 9000, 1e-3),  # the default: a constant lr, as in the paper and the code
    (1e-4, 0, 1e-3),
    (1e-4, 5000, 5.5e-4),  # halfway down the linear decay
    (1e-4, 20_000, 1e-4),  # constant after the schedule
])
def test_lr_decay_sets_the_size_of_every_optimizer_step(lr_final, step, expected_lr):
    # Adam's first step moves every parameter with a nonzero gradient by lr (to within eps): the step size
    # shows the lr in force for the world model, the critics and reward, and the policy alike.
    cfg = tdmpc_config(mlp_dim=MLP, horizon=H, batch_size=B, lr=1e-3, lr_final=lr_final, lr_schedule_steps=10_000,
                      update_freq=10 ** 9)
    wm = make_world()
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters(), lr=cfg.lr), cfg, discrete=True)
    perturb_last_layers(agent.heads)
    modules = {"world model": wm.dynamics, "reward": agent.heads.reward, "critics": agent.heads.q,
               "policy": agent.heads.policy}
    before = {name: [p.detach().clone() for p in m.parameters()] for name, m in modules.items()}
    agent.update(make_batch(), step=step)
    for name, module in modules.items():
        moved = torch.cat([(p.detach() - p0).abs().flatten() for p, p0 in zip(module.parameters(), before[name])])
        assert moved.max().item() == pytest.approx(expected_lr, rel=1e-3), name


def test_lr_final_must_not_exceed_lr():
    from drago.config import ConfigError, load_config
    with pytest.raises(ConfigError, match="agent.tdmpc.lr_final"):
        load_config("smoke", overrides=["agent.tdmpc.lr_final=1e-2"])
    assert load_config("smoke", overrides=["agent.tdmpc.lr_final=1e-4"]).agent.tdmpc.lr_final == 1e-4
