"""PETS beside TD-MPC on the grid: ms per planned action and per update at the same network width.

Both agents are built the way a run builds them (``drago.agent.factory``) from the CPU grid presets,
``minigrid-cpu`` for TD-MPC and ``minigrid-pets-cpu`` for PETS, with the hidden width set to each value of
``--widths`` (TD-MPC's ``agent.tdmpc.mlp_dim``, PETS's ``agent.pets.hidden``). Their planners keep their presets'
budgets, which differ by design (TD-MPC: short horizon, value bootstrap and policy samples; PETS: a longer
horizon over particles and no value), so the table also prints the model evaluations one action costs.

Each round times one call of every (agent, width, component) in turn, so a slow spell of the machine hits
all of them alike; the figure is the median over ``--rounds``. Acting is timed past the seed phase, at the
full horizon, on the first step of an episode (no warm start); an update is one gradient step on a batch
sampled from a buffer of random-action episodes (TD-MPC: its world model and heads; PETS: its ensemble and
reward head).

    .venv/bin/python benchmarks/bench_pets.py [--widths 64 128] [--rounds 30] [--threads 2] [--csv out.csv]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np
import torch

from drago.agent.buffer import EpisodeReplay
from drago.agent.factory import build_agent, build_world_model, build_world_optimizer, replay_horizon
from drago.config import load_config
from drago.envs import env_spec, make_env
from drago.envs.episodes import run_episode
from drago.training.rundir import write_rows_csv

PRESETS = {"tdmpc": ("minigrid-cpu", "agent.tdmpc.mlp_dim"), "pets": ("minigrid-pets-cpu", "agent.pets.hidden")}


def model_calls_per_action(cfg) -> int:
    """One-step model evaluations one planned action runs (samples x horizon x particles x iterations)."""
    if cfg.agent.kind == "pets":
        p = cfg.agent.pets
        return p.iterations * p.population * p.particles * p.horizon
    t = cfg.agent.tdmpc
    return t.iterations * (t.num_samples + int(t.mixture_coef * t.num_samples)) * t.horizon


def build(kind: str, width: int, seed: int = 0) -> dict:
    """An agent of ``kind`` at ``width`` with a filled buffer, and the two calls to time."""
    preset, key = PRESETS[kind]
    cfg = load_config(preset, [f"{key}={width}"], method="continual")
    spec = env_spec(cfg.env.domain)
    torch.manual_seed(seed)
    device = torch.device(cfg.train.device)
    world_model = build_world_model(cfg, spec, device)
    optimizer = build_world_optimizer(cfg, world_model)
    task = cfg.env.tasks[0]
    agent = build_agent(cfg, spec, world_model, optimizer, task=task)
    L, B = cfg.env.episode_length, cfg.agent.batch_size
    buffer = EpisodeReplay(20 * L, spec.obs_dim, spec.action_dim, replay_horizon(cfg), L, cfg.agent.per_alpha,
                           cfg.agent.per_beta, device=device)
    env = make_env(cfg.env.domain, task, cfg.env.dense_reward, action_repeat=cfg.env.action_repeat)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(8):
        ep = run_episode(env, L, lambda obs, t: agent.random_action(rng))
        buffer.add_episode(ep.obs, ep.actions, ep.rewards)
    obs = np.asarray(env.reset(seed=seed)[0])
    step = max(cfg.agent.seed_steps, cfg.agent.tdmpc.horizon_schedule_steps, cfg.agent.tdmpc.std_schedule_steps) + 10 * L

    def update():
        batch = buffer.sample(B, rng)
        out = agent.update(batch, step, train_world_model=True)
        buffer.update_priorities(batch.indices, out["priority"])

    return {"cfg": cfg, "act": lambda: agent.act(obs, step, eval_mode=False, first_step=True), "update": update,
            "params": sum(p.numel() for p in world_model.parameters())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", nargs="+", type=int, default=[64, 128])
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--csv", default=None, help="also write the table to this file")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    agents = {(kind, w): build(kind, w) for w in args.widths for kind in PRESETS}
    samples: dict[tuple, list[float]] = {(k, w, c): [] for (k, w) in agents for c in ("act", "update")}
    for fn in [a[c] for a in agents.values() for c in ("act", "update")]:
        fn()  # warm-up: first-call allocations and lazy initialisation
    for _ in range(args.rounds):
        for (kind, width, component), times in samples.items():
            fn = agents[(kind, width)][component]
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)

    print(f"torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}, "
          f"median of {args.rounds} alternating rounds")
    header = ["agent", "width", "world_model_params", "model_calls_per_action", "batch", "ms_per_action",
              "ms_per_update"]
    rows = []
    for (kind, width), a in agents.items():
        cfg = a["cfg"]
        rows.append([kind, width, a["params"], model_calls_per_action(cfg), cfg.agent.batch_size,
                     round(1e3 * statistics.median(samples[(kind, width, "act")]), 2),
                     round(1e3 * statistics.median(samples[(kind, width, "update")]), 2)])
    print(f"{'agent':<7}{'width':>6}{'model params':>14}{'model calls/action':>20}{'batch':>7}"
          f"{'ms/action':>11}{'ms/update':>11}")
    for r in rows:
        print(f"{r[0]:<7}{r[1]:>6}{r[2]:>14}{r[3]:>20}{r[4]:>7}{r[5]:>11.2f}{r[6]:>11.2f}")
    if args.csv:
        write_rows_csv([dict(zip(header, row)) for row in rows], tuple(header), args.csv)


if __name__ == "__main__":
    main()
