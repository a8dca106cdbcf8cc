"""Behaviour tests for the sum tree and the prioritized episode replay (paper §2; docs: Design, the agent)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drago.agent.buffer import Batch, EpisodeReplay, SumTree
from helpers import filled_buffer

OBS_DIM, ACT_DIM = 3, 2


def make_episode(ep_id: int, length: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Episode whose entries encode (episode id, step) so gathers can be checked."""
    steps = np.arange(length + 1, dtype=np.float32)
    obs = np.stack([np.full(length + 1, ep_id, np.float32), steps, -steps], axis=1)
    actions = np.stack([np.full(length, ep_id, np.float32), steps[:-1] + 0.5], axis=1)
    rewards = ep_id * 1000.0 + steps[:-1]
    return obs, actions, rewards.astype(np.float32)


def make_buffer(n_episodes: int, length: int = 20, horizon: int = 4, capacity: int = 200, **kw):
    buf = EpisodeReplay(capacity, OBS_DIM, ACT_DIM, horizon, length, **kw)
    for e in range(n_episodes):
        buf.add_episode(*make_episode(e, length))
    return buf


def assert_batches_equal(a: Batch, b: Batch) -> None:
    for name in ("obs", "actions", "rewards", "next_obs", "weights"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    np.testing.assert_array_equal(a.indices, b.indices)


# ---------------------------------------------------------------- SumTree
def test_sumtree_total_and_find_hand_computed():
    tree = SumTree(5)
    tree.update(np.arange(5), np.array([1.0, 0.0, 2.0, 3.0, 0.0]))
    assert tree.total == pytest.approx(6.0)
    prefix = np.array([-1.0, 0.0, 0.999, 1.0, 2.999, 3.0, 5.999, 6.0, 100.0])
    # Zero leaves (1, 4) and padding leaves (5..7) are never returned, even at/after total.
    np.testing.assert_array_equal(tree.find(prefix), [0, 0, 0, 2, 2, 3, 3, 3, 3])
    np.testing.assert_allclose(tree.values(np.array([0, 2, 3])), [1.0, 2.0, 3.0])
    assert tree[3] == 3.0
    assert tree.max == 3.0


def test_sumtree_updates_duplicates_and_running_max():
    tree = SumTree(7)
    tree.update(np.array([2, 2, 5]), np.array([4.0, 1.5, 2.0]))  # last write wins
    assert tree[2] == 1.5
    assert tree.total == pytest.approx(3.5)
    assert tree.max == 2.0
    tree.update(np.array([5]), np.array([9.0]))
    tree.update(np.array([5]), np.array([2.0]))
    assert tree.max == 9.0  # running max, not the current max
    tree.update(np.array([5]), np.array([0.0]))
    assert tree.total == pytest.approx(1.5)
    with pytest.raises(IndexError):
        tree.update(np.array([7]), np.array([1.0]))
    with pytest.raises(ValueError):
        tree.update(np.array([0]), np.array([np.nan]))


def test_sumtree_many_updates_keep_exact_total():
    rng = np.random.default_rng(0)
    tree = SumTree(1000)
    ref = np.zeros(1000)
    for _ in range(200):
        idx = rng.integers(0, 1000, 64)
        vals = rng.random(64)
        tree.update(idx, vals)
        for i, v in zip(idx, vals):  # sequential writes: last duplicate wins
            ref[i] = v
    np.testing.assert_array_equal(tree.values(np.arange(1000)), ref)
    assert tree.total == pytest.approx(ref.sum(), rel=1e-12)


def test_sumtree_sampling_frequencies_match_values():
    rng = np.random.default_rng(1)
    cap = 37
    p = rng.random(cap) * 5
    p[[3, 10, 36]] = 0.0
    alpha = 0.6
    tree = SumTree(cap)
    tree.update(np.arange(cap), p**alpha)
    n = 200_000
    leaves = tree.find(rng.random(n) * tree.total)
    freq = np.bincount(leaves, minlength=cap) / n
    expected = p**alpha / np.sum(p**alpha)
    assert freq[[3, 10, 36]].sum() == 0
    assert np.max(np.abs(freq - expected)) < 0.005
    chi2 = np.sum((freq - expected)[expected > 0] ** 2 / expected[expected > 0]) * n
    assert chi2 < 90  # 33 dof; p(chi2 > 90) is ~1e-7


# ------------------------------------------------------------- PER buffer
def test_capacity_rounding_and_fifo_sizes():
    buf = EpisodeReplay(95, OBS_DIM, ACT_DIM, horizon=4, episode_length=20)
    assert buf.capacity == 80 and buf.max_episodes == 4
    assert len(buf) == 0 and buf.num_episodes == 0
    for e in range(6):
        buf.add_episode(*make_episode(e, 20))
        assert buf.num_episodes == min(e + 1, 4)
        assert len(buf) == 20 * buf.num_episodes


def test_sampling_distribution_follows_p_alpha():
    L, H = 6, 2
    buf = make_buffer(3, length=L, horizon=H, capacity=18)
    valid = np.array([e * L + s for e in range(3) for s in range(L - H)])
    raw = np.linspace(0.1, 3.0, valid.size)
    buf.update_priorities(valid, raw)
    expected = np.zeros(buf.capacity)
    expected[valid] = (raw + 1e-6) ** 0.6
    expected /= expected.sum()

    rng = np.random.default_rng(2)
    counts = np.zeros(buf.capacity)
    n_batches, bs = 200, 512
    for _ in range(n_batches):
        counts += np.bincount(buf.sample(bs, rng).indices, minlength=buf.capacity)
    freq = counts / (n_batches * bs)
    assert counts[expected == 0].sum() == 0
    assert np.max(np.abs(freq - expected)) < 0.004


def test_importance_weights_hand_made_case():
    L, H = 4, 1
    buf = make_buffer(2, length=L, horizon=H, capacity=8)  # N = 8 stored transitions
    valid = np.array([0, 1, 2, 4, 5, 6])
    raw = np.array([1.0, 2.0, 4.0, 8.0, 0.5, 3.0])
    buf.update_priorities(valid, raw)
    pa = (raw + 1e-6) ** 0.6
    prob = dict(zip(valid.tolist(), pa / pa.sum()))

    batch = buf.sample(64, np.random.default_rng(3))
    w = np.array([(8 * prob[i]) ** -0.4 for i in batch.indices])
    np.testing.assert_allclose(batch.weights.numpy(), w / w.max(), rtol=1e-6)
    assert batch.weights.max().item() == pytest.approx(1.0)
    assert batch.weights.dtype == torch.float32


@pytest.mark.parametrize("n_episodes", [3, 5, 11])  # 5 fills exactly, 11 wraps twice+
def test_sequences_stay_inside_one_episode(n_episodes: int):
    L, H, cap_eps = 12, 4, 5
    buf = make_buffer(n_episodes, length=L, horizon=H, capacity=cap_eps * L + 7)
    stored_ids = set(range(max(0, n_episodes - cap_eps), n_episodes))
    rng = np.random.default_rng(4)
    seen_last_step = False
    for _ in range(30):
        b = buf.sample(256, rng)
        assert b.obs.shape == (256, OBS_DIM)
        assert b.actions.shape == (H + 1, 256, ACT_DIM)
        assert b.rewards.shape == (H + 1, 256)
        assert b.next_obs.shape == (H + 1, 256, OBS_DIM)
        assert b.weights.shape == (256,)
        step = b.indices % L
        assert np.all(step <= L - 1 - H), "sampled a start in the last H steps"
        assert np.all(b.indices < len(buf))
        ep = b.obs[:, 0]
        assert set(ep.long().tolist()) <= stored_ids
        np.testing.assert_array_equal(b.obs[:, 1].numpy(), step)
        for t in range(H + 1):
            # All of a_t, r_t, s_{t+1} come from the start's episode at step start+t.
            assert torch.equal(b.actions[t, :, 0], ep)
            np.testing.assert_array_equal(b.actions[t, :, 1].numpy(), step + t + 0.5)
            np.testing.assert_array_equal(b.rewards[t].numpy(), ep.numpy() * 1000 + step + t)
            assert torch.equal(b.next_obs[t, :, 0], ep)
            np.testing.assert_array_equal(b.next_obs[t, :, 1].numpy(), step + t + 1)
            np.testing.assert_array_equal(b.next_obs[t, :, 2].numpy(), -(step + t + 1))
        # s_L (the separately stored last observation) is reached by t = H.
        seen_last_step |= bool(np.any(step + H + 1 == L))
    assert seen_last_step


def test_last_slot_wraparound_final_obs():
    # A start in the last slot's final valid step must read s_L from last_obs,
    # not wrap around to slot 0.
    L, H = 5, 2
    buf = make_buffer(2, length=L, horizon=H, capacity=10)
    valid = np.arange(10)[np.arange(10) % L < L - H]
    prio = np.full(valid.size, 1e-9)
    prio[valid == 2 * L - H - 1] = 1e6
    buf.update_priorities(valid, prio)
    b = buf.sample(32, np.random.default_rng(5))
    assert np.all(b.indices == 2 * L - H - 1)
    np.testing.assert_array_equal(b.next_obs[H, :, :2].numpy(), np.tile([1.0, L], (32, 1)))


def test_update_priorities_changes_distribution_and_new_episodes_get_max():
    L, H = 10, 3
    buf = make_buffer(2, length=L, horizon=H, capacity=100)
    rng = np.random.default_rng(6)
    assert np.all(buf.priorities(np.arange(L - H)) == 1.0)  # empty-buffer max is 1
    b = buf.sample(128, rng)
    buf.update_priorities(b.indices, torch.full((128,), 0.01))
    buf.update_priorities(np.array([13]), np.array([50.0]))
    counts = np.bincount(buf.sample(4096, rng).indices, minlength=buf.capacity)
    assert counts[13] > 0.5 * 4096

    # Tail indices are ignored: their priority stays zero.
    tail = np.array([L - 1, L - H, 2 * L - 1])
    buf.update_priorities(tail, np.full(3, 100.0))
    assert np.all(buf.priorities(tail) == 0.0)
    assert buf.max_priority == pytest.approx(50.0 + 1e-6)

    buf.add_episode(*make_episode(2, L))
    new = buf.priorities(np.arange(2 * L, 3 * L))
    np.testing.assert_allclose(new[: L - H], (50.0 + 1e-6) ** 0.6)
    assert np.all(new[L - H :] == 0.0)


def test_fifo_overwrite_resets_priorities():
    L, H = 6, 2
    buf = make_buffer(2, length=L, horizon=H, capacity=12)
    buf.update_priorities(np.array([0, 1]), np.array([1e-9, 1e-9]))
    buf.add_episode(*make_episode(7, L))  # overwrites slot 0
    assert buf.num_episodes == 2
    np.testing.assert_allclose(buf.priorities(np.arange(L - H)), buf.max_priority**0.6)
    obs, act = buf.sample_transitions(500, np.random.default_rng(7))
    assert set(obs[:, 0].long().tolist()) == {7, 1}
    assert obs.shape == (500, OBS_DIM) and act.shape == (500, ACT_DIM)
    assert torch.equal(act[:, 1], obs[:, 1] + 0.5)  # rows pair (s_t, a_t)


def test_accepts_torch_input():
    buf = EpisodeReplay(40, OBS_DIM, ACT_DIM, 2, 10)
    obs, act, rew = make_episode(0, 10)
    buf.add_episode(torch.from_numpy(obs).double(), torch.from_numpy(act), torch.from_numpy(rew))
    assert len(buf) == 10
    b = buf.sample(4, np.random.default_rng(0))
    assert b.obs.dtype == torch.float32 and b.obs.device == torch.device("cpu")


def test_determinism_and_state_dict_roundtrip():
    def run(buf: EpisodeReplay, rng: np.random.Generator, n: int) -> list[Batch]:
        out = []
        for _ in range(n):
            b = buf.sample(64, rng)
            buf.update_priorities(b.indices, rng.random(64) * 3)
            out.append(b)
        return out

    a = make_buffer(7, capacity=100)
    b = make_buffer(7, capacity=100)
    for x, y in zip(run(a, np.random.default_rng(8), 5), run(b, np.random.default_rng(8), 5)):
        assert_batches_equal(x, y)

    state = a.state_dict()
    rng_state = np.random.default_rng(9).bit_generator.state
    c = EpisodeReplay(100, OBS_DIM, ACT_DIM, 4, 20)
    c.load_state_dict(state)
    assert len(c) == len(a) and c.num_episodes == a.num_episodes
    rng_a, rng_c = np.random.default_rng(), np.random.default_rng()
    rng_a.bit_generator.state = rng_state
    rng_c.bit_generator.state = rng_state
    a.add_episode(*make_episode(99, 20))
    c.add_episode(*make_episode(99, 20))
    for x, y in zip(run(a, rng_a, 5), run(c, rng_c, 5)):
        assert_batches_equal(x, y)
    # The state is a copy: mutating the buffer afterwards does not change it.
    assert not torch.equal(state["obs"], a.state_dict()["obs"])

    with pytest.raises(ValueError):
        EpisodeReplay(100, OBS_DIM, ACT_DIM, 3, 20).load_state_dict(state)


def test_batch_concat_and_with_rewards():
    buf = make_buffer(3)
    rng = np.random.default_rng(10)
    x, y = buf.sample(8, rng), buf.sample(5, rng)
    z = x.concat(y)
    assert z.batch_size == 13
    assert z.actions.shape == (5, 13, ACT_DIM) and z.next_obs.shape == (5, 13, OBS_DIM)
    assert torch.equal(z.rewards[:, 8:], y.rewards) and torch.equal(z.obs[:8], x.obs)
    np.testing.assert_array_equal(z.indices, np.concatenate([x.indices, y.indices]))
    r = torch.zeros_like(z.rewards)
    z2 = z.with_rewards(r)
    assert z2.rewards is r and z.rewards is not r and z2.obs is z.obs
    with pytest.raises(ValueError):
        z.with_rewards(torch.zeros(3))


def test_bad_input_raises():
    with pytest.raises(ValueError):
        EpisodeReplay(100, OBS_DIM, ACT_DIM, horizon=5, episode_length=5)
    with pytest.raises(ValueError):
        EpisodeReplay(10, OBS_DIM, ACT_DIM, horizon=2, episode_length=20)
    buf = EpisodeReplay(100, OBS_DIM, ACT_DIM, horizon=4, episode_length=10)
    with pytest.raises(ValueError):
        buf.add_episode(*make_episode(0, 4))  # L <= H
    with pytest.raises(ValueError):
        buf.add_episode(*make_episode(0, 8))  # L != episode_length
    obs, act, rew = make_episode(0, 10)
    with pytest.raises(ValueError):
        buf.add_episode(obs[:-1], act, rew)  # missing s_L
    with pytest.raises(ValueError):
        buf.add_episode(obs[:, :2], act, rew)
    with pytest.raises(ValueError):
        buf.add_episode(obs, act[:, :1], rew)
    with pytest.raises(ValueError):
        buf.add_episode(obs, act, rew[:, None])
    with pytest.raises(ValueError):
        buf.sample(4, np.random.default_rng(0))  # empty
    buf.add_episode(obs, act, rew)
    with pytest.raises(ValueError):
        buf.update_priorities(np.array([0, 1]), np.array([1.0]))
    with pytest.raises(ValueError):
        buf.update_priorities(np.array([0]), np.array([np.nan]))


# ---------------------------------------------------------------- host and device priorities
def test_device_priorities_sample_and_update_like_the_host_tree():
    """The accelerator path (priorities kept on the device) run on the CPU: the same batches, weights
    and stored priorities as the host sum tree, and checkpoints that load into either."""
    host, device = filled_buffer(device_priorities=False), filled_buffer(device_priorities=True)
    assert device.device_priorities and not host.device_priorities
    rh, rd = np.random.default_rng(1), np.random.default_rng(1)
    for k in range(30):
        bh, bd = host.sample(64, rh), device.sample(64, rd)
        assert isinstance(bd.indices, torch.Tensor)
        np.testing.assert_array_equal(bh.indices, bd.indices.numpy())
        torch.testing.assert_close(bh.weights, bd.weights)
        assert torch.equal(bh.next_obs, bd.next_obs) and torch.equal(bh.actions, bd.actions)
        new = torch.rand(64) * 3  # duplicated indices: the last write wins on both paths
        host.update_priorities(bh.indices, new)
        device.update_priorities(bd.indices, new)
        if k % 10 == 9:
            for buf in (host, device):
                buf.add_episode(np.ones((21, OBS_DIM)), np.ones((20, ACT_DIM)), np.ones(20))
    every = np.arange(host.capacity)
    np.testing.assert_allclose(device.priorities(every), host.priorities(every), rtol=1e-12)
    assert device.max_priority == pytest.approx(host.max_priority, rel=1e-12)
    assert isinstance(bd.concat(bd).indices, torch.Tensor)
    for source, target in ((device, filled_buffer(device_priorities=False)), (host, filled_buffer(device_priorities=True))):
        target.load_state_dict(source.state_dict())
        np.testing.assert_allclose(target.priorities(every), source.priorities(every), rtol=1e-12)
        assert target.max_priority == source.max_priority
    with pytest.raises(RuntimeError, match="finite and non-negative"):
        device.update_priorities(bd.indices, torch.full((64,), float("nan")))
