"""Speed of the agent's hot paths, measured in one process.

Prints the machine's float32 matmul GFLOP/s, then for each preset: ms per TD-MPC update, ms per
planned action, and env steps per second of a training iteration (one learner episode plus its
updates). The iteration is measured for real on small presets; for presets where one iteration takes
over a minute on a CPU it is composed from the measured parts (pass --full-iteration to time it).

    .venv/bin/python benchmarks/bench_speed.py [--presets minigrid minigrid-cpu] [--threads 2] [--json out.json]

Not part of the test suite: timings here vary by +-25% between identical runs on a shared 2-core VM.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import numpy as np
import torch

from drago.agent.agent import Agent
from drago.agent.buffer import EpisodeReplay
from drago.config import load_config
from drago.envs import env_spec, make_env
from drago.train.trainer import build_world_model, run_episode


def matmul_gflops(n: int = 1024, repeats: int = 20) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    for _ in range(3):
        a @ b
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t0)
    return 2 * n**3 / statistics.median(times) / 1e9


def _sync() -> None:
    """Wait for queued GPU work, so a timing covers the kernels and not only their launch."""
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def timed(fn, repeats: int) -> float:
    """Median seconds of ``fn`` over ``repeats`` calls, after one warm-up call."""
    fn()
    samples = []
    for _ in range(repeats):
        _sync()
        t0 = time.perf_counter()
        fn()
        _sync()
        samples.append(time.perf_counter() - t0)
    return statistics.median(samples)


def bench_preset(name: str, repeats: int, full_iteration: bool, device_name: str | None = None) -> dict:
    cfg = load_config(name)
    if device_name is not None:
        cfg.train.device = device_name
    spec = env_spec(cfg.env.domain)
    device = torch.device(cfg.train.device)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    world_model = build_world_model(cfg, spec, device)
    optimizer = torch.optim.Adam(world_model.dynamics.parameters(), lr=cfg.agent.lr)
    agent = Agent(world_model, optimizer, cfg.agent, spec.discrete)
    L = cfg.env.episode_length
    buffer = EpisodeReplay(50 * L, spec.obs_dim, spec.action_dim, cfg.agent.horizon, L, device=device)
    env = make_env(cfg.env.domain, cfg.env.tasks[0], cfg.env.dense_reward)
    env.reset(seed=0)
    for _ in range(max(20, cfg.agent.batch_size // L + 1)):
        ep = run_episode(env, L, lambda obs, t: agent.random_action(rng))
        buffer.add_episode(ep.obs, ep.actions, ep.rewards)

    late_step = 10 * cfg.agent.horizon_schedule_steps  # full planning horizon

    def update():
        batch = buffer.sample(cfg.agent.batch_size, rng)
        metrics = agent.update(batch, late_step)
        buffer.update_priorities(batch.indices, metrics["priority"])

    obs = np.asarray(env.reset()[0])
    update_s = timed(update, repeats)
    act_s = timed(lambda: agent.act(obs, late_step, eval_mode=False, first_step=True), repeats)
    env_s = timed(lambda: env.step(agent.random_action(rng)), 200)
    U = cfg.updates_per_episode
    composed = L * (act_s + env_s) + U * update_s
    result = {"preset": name, "mlp_dim": cfg.agent.mlp_dim, "horizon": cfg.agent.horizon,
              "batch_size": cfg.agent.batch_size, "planner_samples": cfg.agent.num_samples,
              "planner_iterations": cfg.agent.iterations, "ms_per_update": update_s * 1e3,
              "ms_per_action": act_s * 1e3, "updates_per_episode": U, "episode_length": L,
              "iteration_s_composed": composed, "env_steps_per_s_composed": L / composed}
    if full_iteration or composed < 20:
        t0 = time.perf_counter()
        ep = run_episode(env, L, lambda o, t: agent.act(o, late_step, eval_mode=False, first_step=t == 0))
        buffer.add_episode(ep.obs, ep.actions, ep.rewards)
        for _ in range(U):
            update()
        measured = time.perf_counter() - t0
        result["iteration_s_measured"] = measured
        result["env_steps_per_s_measured"] = L / measured
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["minigrid", "minigrid-cpu"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--full-iteration", action="store_true", help="time a real iteration on every preset")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: each preset's)")
    parser.add_argument("--json", default=None, help="also write the results to this file")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    gflops = matmul_gflops()
    print(f"torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}")
    print(f"float32 matmul (1024^3): {gflops:.1f} GFLOP/s")
    rows = [bench_preset(p, args.repeats, args.full_iteration, args.device) for p in args.presets]
    header = f"{'preset':<14}{'width':>6}{'H':>4}{'batch':>6}{'ms/update':>11}{'ms/action':>11}{'env steps/s':>13}  (iteration)"
    print(header)
    for r in rows:
        if "env_steps_per_s_measured" in r:
            sps, how = r["env_steps_per_s_measured"], f"measured {r['iteration_s_measured']:.1f} s"
        else:
            sps, how = r["env_steps_per_s_composed"], f"composed {r['iteration_s_composed']:.1f} s"
        print(f"{r['preset']:<14}{r['mlp_dim']:>6}{r['horizon']:>4}{r['batch_size']:>6}{r['ms_per_update']:>11.1f}"
              f"{r['ms_per_action']:>11.1f}{sps:>13.1f}  ({how})")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"matmul_gflops": gflops, "threads": args.threads, "torch": torch.__version__,
                       "presets": rows}, handle, indent=2)


if __name__ == "__main__":
    main()
