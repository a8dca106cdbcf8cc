"""Speed of the agent's hot paths and of a DRAGO task-2 iteration, measured in one process.

For each preset it prints and records:

* ms per planned action (the learner's, and the reviewer's with its count bonus), at the full horizon;
* ms per TD-MPC update (a task-1 learner update that also trains the world model);
* ms per full DRAGO gradient step in task 2: learner update, reviewer update on the 2B combined rows,
  VAE step and rehearsal step (``Drago.gradient_step``), with an old world model, an old VAE and a
  reviewer set up through the method's own ``begin_task`` after a fake previous task;
* env steps per second of a whole task-2 iteration (learner episode + reviewer episode + updates):
  measured for real when the composed estimate is under ``--measure-limit`` seconds, otherwise
  composed from the measured parts (``--full-iteration`` measures it anyway);
* peak memory: the process's peak resident set size while the preset ran, and CUDA's max allocated;
* minor page faults per call: fresh pages the kernel had to zero-fill, zero once malloc keeps freed memory;
* utilisation: the FLOPs each component must do, counted from layer shapes by
  ``torch.utils.flop_counter.FlopCounterMode`` on one call, over its measured time, as a fraction of the
  machine's float32 matmul FLOP/s measured in this process just before the preset. The FLOP-limit time
  is FLOPs / matmul FLOP/s; for the iteration, ``measured / limit`` is the measured time over the sum
  of its parts' FLOP-limit times (1.0 would be pure matmul at the machine's peak);
* matmul kernels alone: each component's matrix multiplies, recorded on one call and replayed at the same
  shapes and strides with nothing in between. It is the time the component cannot go below on this
  machine while its maths stays the same (small matmuls run far below the n=1024 FLOP/s), and
  ``ms - matmul ms`` is all the rest: elementwise kernels, normalisation, the optimizer, dispatch.

    .venv/bin/python benchmarks/bench_speed.py [--presets minigrid minigrid-cpu cheetah-cpu] [--threads 2]
        [--repeats 10] [--device cpu|cuda] [--set agent.tdmpc.precision=bfloat16 ...] [--json new.json]
        [--compare old.json]

``--compare OLD.json`` prints new/old ratios of every metric both files have (ms: below 1 is faster;
steps/s and utilisation: above 1 is better). Not part of the test suite: on a shared 2-core VM timings
vary by +-25% between identical runs, so compare variants run close together, or alternate them.
"""

from __future__ import annotations

import argparse
import gc
import json
import platform
import resource
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from drago.agent.agent import Agent
from drago.agent.buffer import EpisodeReplay
from drago.agent.speed import resolve_speed
from drago.config import load_config
from drago.continual.base import Budget, TaskState, buffer_capacity
from drago.continual.drago import Drago
from drago.envs import env_spec, make_env
from drago.training.resources import PeakMemory, keep_freed_memory
from drago.agent.networks import build_world_model
from drago.envs.episodes import run_episode

DEFAULT_PRESETS = ("minigrid", "minigrid-cpu", "cheetah-cpu")


# ---- timing and the machine --------------------------------------------------------------------------
def _sync(device: torch.device) -> None:
    """Wait for queued GPU work, so a timing covers the kernels and not only their launch."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _minor_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def timed(fn, repeats: int, device: torch.device) -> tuple[float, float]:
    """(median seconds, minor page faults per call) of ``fn`` over ``repeats`` calls, after one warm-up call.

    Page faults are the process's: each is a fresh page the kernel zero-fills, work the FLOP count does not see.
    """
    fn()
    samples = []
    faults = _minor_faults()
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        samples.append(time.perf_counter() - t0)
    return statistics.median(samples), (_minor_faults() - faults) / repeats


def matmul_flops(device: torch.device, dtype: torch.dtype = torch.float32, n: int = 1024, repeats: int = 20) -> float:
    """FLOP/s of an n x n x n matmul (median of ``repeats``)."""
    a = torch.randn(n, n, device=device, dtype=dtype)
    b = torch.randn(n, n, device=device, dtype=dtype)
    return 2 * n**3 / timed(lambda: a @ b, repeats, device)[0]


def count_flops(fn) -> int:
    """FLOPs of one call of ``fn`` (forward and backward matmuls), counted from shapes."""
    with FlopCounterMode(display=False) as counter:
        fn()
    return int(counter.get_total_flops())


_MATMULS = {torch.ops.aten.mm.default, torch.ops.aten.addmm.default, torch.ops.aten.bmm.default,
            torch.ops.aten.baddbmm.default}  # the ops FlopCounterMode counts for these networks


class MatmulRecorder(TorchDispatchMode):
    """Records the matrix multiplies one call runs (op, argument layouts) so they can be replayed alone.

    Only layouts are kept: replay builds one random tensor per distinct (shape, strides, dtype, device),
    so transposed weights and broadcast biases keep the memory layout, and so the kernel, they had.
    """

    def __init__(self):
        super().__init__()
        self.calls: list[tuple] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in _MATMULS:
            layout = [(tuple(a.shape), a.stride(), a.dtype, a.device) if isinstance(a, torch.Tensor) else a
                      for a in args]
            self.calls.append((func, layout, dict(kwargs)))
        return func(*args, **kwargs)

    def replay_fn(self):
        """A zero-argument callable that runs the recorded matmuls, in order, on stand-in tensors."""
        tensors: dict[tuple, torch.Tensor] = {}

        def stand_in(layout):
            if layout not in tensors:
                shape, stride, dtype, device = layout
                span = 0 if 0 in shape else 1 + sum((n - 1) * st for n, st in zip(shape, stride))  # storage reached
                tensors[layout] = torch.randn(span, dtype=dtype, device=device).as_strided(shape, stride)
            return tensors[layout]

        calls = [(func, [stand_in(a) if isinstance(a, tuple) else a for a in layout], kwargs)
                 for func, layout, kwargs in self.calls]

        def replay():
            for func, args, kwargs in calls:
                func(*args, **kwargs)
        return replay


def record_matmuls(fn) -> MatmulRecorder:
    with MatmulRecorder() as recorder:
        fn()
    return recorder


# ---- a DRAGO task-2 state ----------------------------------------------------------------------------
def task_two(cfg, device: torch.device, seed: int = 0) -> tuple[Drago, TaskState]:
    """DRAGO at the start of task 2, with data to sample: the state every task-2 component runs in.

    The previous task is faked through the method's own carry state (its VAE, the default threshold,
    one task seen); ``begin_task`` then builds the frozen old world model and VAE, the reviewer, its
    buffer and its counts, as after a real task 1. Both buffers get random-action episodes.
    """
    spec = env_spec(cfg.env.domain)
    torch.manual_seed(seed)
    method = Drago(cfg, spec, device)
    method.load_carry_state({"vae": method.vae.state_dict(), "threshold": cfg.method.reviewer.initial_threshold,
                             "tasks_seen": 1})
    world_model = build_world_model(cfg, spec, device)
    world_optimizer = torch.optim.Adam(world_model.dynamics.parameters(), lr=cfg.agent.lr)
    learner = Agent(world_model, world_optimizer, cfg.agent, spec.discrete)
    budget = Budget.from_config(cfg)
    L = cfg.env.episode_length
    buffer = EpisodeReplay(buffer_capacity(budget.max_learner_steps, L), spec.obs_dim, spec.action_dim,
                           cfg.agent.tdmpc.horizon, L, cfg.agent.per_alpha, cfg.agent.per_beta, device=device)
    name = cfg.env.tasks[min(1, len(cfg.env.tasks) - 1)]
    env = make_env(cfg.env.domain, name, cfg.env.dense_reward, action_repeat=cfg.env.action_repeat)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    task = TaskState(index=1, name=name, world_model=world_model, world_optimizer=world_optimizer,
                     learner=learner, buffer=buffer, rng=rng, env=env, budget=budget)
    method.begin_task(task)
    episodes = max(4, -(-cfg.agent.batch_size // (L - cfg.agent.tdmpc.horizon)) + 1)
    for _ in range(episodes):
        ep = run_episode(env, L, lambda obs, t: learner.random_action(rng))
        buffer.add_episode(ep.obs, ep.actions, ep.rewards)
        task.step = 0  # the reviewer's episode is random-action (seed phase) and labelled as in training
        method.collect(task)
    task.step = late_step(cfg)
    return method, task


def late_step(cfg) -> int:
    """A task step past the seed phase and the horizon schedule: planning at the full horizon."""
    t = cfg.agent.tdmpc
    return max(cfg.agent.seed_steps, t.horizon_schedule_steps, t.std_schedule_steps) + 10 * cfg.env.episode_length


def components(method: Drago, task: TaskState, cfg) -> dict:
    """name -> (zero-argument callable, calls per task-2 iteration) of every timed component."""
    L, U = cfg.env.episode_length, cfg.updates_per_episode
    step = task.step
    obs = np.asarray(task.env.reset()[0])
    rng = np.random.default_rng(1)
    parts = method.task_parts(task)
    bonus = parts.counts.bonus if parts.counts is not None else None
    reviewer = parts.reviewer
    B = cfg.agent.batch_size
    freq = cfg.method.rehearsal.freq

    def learner_update():  # task 1 (or continual): the learner also trains the world model
        batch = task.buffer.sample(B, rng)
        out = task.learner.update(batch, step, train_world_model=True)
        task.buffer.update_priorities(batch.indices, out["priority"])

    def rehearsal_step():
        loss = method._rehearsal(task)
        task.world_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        task.world_optimizer.step()

    def vae_step():
        method._vae_step(parts, task.buffer.sample(B, rng).concat(parts.reviewer_buffer.sample(B, rng)))

    u0 = step - step % (freq * cfg.agent.tdmpc.update_freq)  # a step with rehearsal and target EMA
    return {
        "act": (lambda: task.learner.act(obs, step, eval_mode=False, first_step=True), L),
        "reviewer_act": (lambda: reviewer.act(obs, step, eval_mode=False, first_step=True, bonus=bonus), L),
        "env_step": (lambda: task.env.step(task.learner.random_action(rng)), 2 * L),
        "update": (learner_update, 0),  # reference only: not part of a task-2 iteration
        "drago_step": (lambda: method.gradient_step(task, u0), U),
        # Parts of drago_step, for the breakdown; the rehearsal runs on 1 of every `freq` steps.
        "vae_step": (vae_step, 0),
        "rehearsal_step": (rehearsal_step, 0),
    }


def measure_iteration(method: Drago, task: TaskState, cfg) -> float:
    """Seconds of one real task-2 iteration: learner episode, reviewer episode, then U gradient steps."""
    L, U = cfg.env.episode_length, cfg.updates_per_episode
    step = task.step
    t0 = time.perf_counter()
    ep = run_episode(task.env, L, lambda o, t: task.learner.act(o, step, eval_mode=False, first_step=t == 0))
    task.buffer.add_episode(ep.obs, ep.actions, ep.rewards)
    method.collect(task)
    for i in range(U):
        method.gradient_step(task, step + i)
    _sync(task.learner.device)
    task.step = step
    return time.perf_counter() - t0


def bench_preset(name: str, args) -> dict:
    overrides = list(args.set or [])
    if args.device is not None:
        overrides.append(f"train.device={args.device}")
    cfg = load_config(name, overrides, method="drago")
    device = torch.device(cfg.train.device)
    cfg, notes = resolve_speed(cfg, device)  # what a run of this preset would use on this machine
    for note in notes:
        print(f"{name}: {note}")
    memory = PeakMemory(device)
    rate = matmul_flops(device)
    memory.start()
    method, task = task_two(cfg, device)
    parts = components(method, task, cfg)
    # FLOPs depend only on shapes: with torch.compile on they are counted on an eager twin.
    if cfg.agent.tdmpc.compile == "true":
        eager = load_config(name, [*overrides, "agent.tdmpc.compile=false", f"agent.tdmpc.precision={cfg.agent.tdmpc.precision}"],
                            method="drago")
        twin_parts = components(*task_two(eager, device), eager)
    else:
        twin_parts = parts

    result = {"preset": name, "device": str(device), "precision": cfg.agent.tdmpc.precision,
              "compile": cfg.agent.tdmpc.compile == "true", "fast_tanh": cfg.agent.tdmpc.fast_tanh, "mlp_dim": cfg.agent.tdmpc.mlp_dim, "horizon": cfg.agent.tdmpc.horizon,
              "batch_size": cfg.agent.batch_size, "planner_samples": cfg.agent.tdmpc.num_samples,
              "planner_iterations": cfg.agent.tdmpc.iterations, "episode_length": cfg.env.episode_length,
              "updates_per_episode": cfg.updates_per_episode, "rehearsal_freq": cfg.method.rehearsal.freq,
              "matmul_gflops": rate / 1e9, "components": {}}
    if cfg.agent.tdmpc.precision == "bfloat16":  # context only: utilisation stays relative to float32
        result["matmul_gflops_bfloat16"] = matmul_flops(device, torch.bfloat16) / 1e9
    for key, (fn, calls) in parts.items():
        repeats = 200 if key == "env_step" else args.repeats
        seconds, faults = timed(fn, repeats, device)
        flops, matmul_s, matmuls = 0, 0.0, 0
        if key != "env_step":
            flops = count_flops(twin_parts[key][0])
            recorder = record_matmuls(twin_parts[key][0])
            matmul_s, matmuls = timed(recorder.replay_fn(), repeats, device)[0], len(recorder.calls)
        result["components"][key] = {
            "ms": seconds * 1e3, "gflop": flops / 1e9, "flop_limit_ms": flops / rate * 1e3,
            "utilisation": flops / seconds / rate, "matmul_ms": matmul_s * 1e3, "matmuls": matmuls,
            "calls_per_iteration": calls, "page_faults": faults}

    c = result["components"]
    L, U, freq = cfg.env.episode_length, cfg.updates_per_episode, cfg.method.rehearsal.freq
    # drago_step was timed on a step with rehearsal; on average only 1 step in `freq` has one.
    skip = (1 - 1 / freq)
    step_s = (c["drago_step"]["ms"] - skip * c["rehearsal_step"]["ms"]) / 1e3
    step_flops = (c["drago_step"]["gflop"] - skip * c["rehearsal_step"]["gflop"]) * 1e9
    composed = L * (c["act"]["ms"] + c["reviewer_act"]["ms"] + 2 * c["env_step"]["ms"]) / 1e3 + U * step_s
    limit = (L * (c["act"]["gflop"] + c["reviewer_act"]["gflop"]) * 1e9 + U * step_flops) / rate
    step_matmul_s = (c["drago_step"]["matmul_ms"] - skip * c["rehearsal_step"]["matmul_ms"]) / 1e3
    matmul_alone = L * (c["act"]["matmul_ms"] + c["reviewer_act"]["matmul_ms"]) / 1e3 + U * step_matmul_s
    env_steps = 2 * L * cfg.env.action_repeat
    iteration = {"env_steps": env_steps, "composed_s": composed, "flop_limit_s": limit, "matmul_alone_s": matmul_alone}
    if args.full_iteration or composed < args.measure_limit:
        iteration["measured_s"] = measure_iteration(method, task, cfg)
        iteration["how"] = "measured"
    else:
        iteration["how"] = "composed"
    seconds = iteration.get("measured_s", composed)
    iteration["env_steps_per_s"] = env_steps / seconds
    iteration["measured_over_limit"] = seconds / limit
    iteration["matmul_alone_share"] = matmul_alone / seconds
    result["iteration"] = iteration
    result["memory"] = memory.read()
    del method, task, parts, twin_parts
    gc.collect()
    return result


# ---- printing and comparing --------------------------------------------------------------------------
def print_table(rows: list[dict]) -> None:
    for r in rows:
        print(f"\n{r['preset']}: width {r['mlp_dim']}, H {r['horizon']}, batch {r['batch_size']}, "
              f"{r['planner_iterations']}x{r['planner_samples']} planner samples, {r['precision']}"
              f"{', compiled' if r['compile'] else ''}{', fast tanh' if r.get('fast_tanh') else ''}, {r['device']}; "
              f"float32 matmul {r['matmul_gflops']:.1f} GFLOP/s"
              + (f" (bfloat16 {r['matmul_gflops_bfloat16']:.1f})" if "matmul_gflops_bfloat16" in r else ""))
        print(f"  {'component':<16}{'ms':>10}{'GFLOP':>9}{'limit ms':>10}{'util':>7}{'mm ms':>10}{'mm %':>6}"
              f"{'x/iter':>8}{'faults':>9}")
        for key, c in r["components"].items():
            util = f"{c['utilisation']:.0%}" if c["gflop"] else "-"
            mm_ms = f"{c['matmul_ms']:.2f}" if c.get("matmuls") else "-"
            mm_share = f"{c['matmul_ms'] / c['ms']:.0%}" if c.get("matmuls") else "-"
            calls = c["calls_per_iteration"] or "-"  # 0: a reference or a part of drago_step
            print(f"  {key:<16}{c['ms']:>10.2f}{c['gflop']:>9.3f}{c['flop_limit_ms']:>10.2f}{util:>7}{mm_ms:>10}"
                  f"{mm_share:>6}{calls:>8}{c['page_faults']:>9.0f}")
        it, mem = r["iteration"], r["memory"]
        seconds = it.get("measured_s", it["composed_s"])
        composed = f" (composed {it['composed_s']:.1f} s)" if it["how"] == "measured" else ""
        print(f"  task-2 iteration ({it['env_steps']} env steps): {seconds:.1f} s {it['how']}{composed}, "
              f"{it['env_steps_per_s']:.1f} env steps/s, "
              f"FLOP limit {it['flop_limit_s']:.1f} s, time/limit {it['measured_over_limit']:.2f}")
        print(f"  its matmul kernels alone: {it['matmul_alone_s']:.1f} s, {it['matmul_alone_share']:.0%} of its time")
        cuda = mem.get("cuda_max_allocated_mib")
        extra = f", CUDA max allocated {cuda:.0f} MiB" if cuda is not None else ""
        print(f"  peak RSS {mem['peak_rss_mib']:.0f} MiB{extra}")


# Metrics of the older JSON format (before the task-2 components), under the new names.
_OLD_NAMES = {"ms_per_update": "components.update.ms", "ms_per_action": "components.act.ms",
              "matmul_gflops": "matmul_gflops"}


def flatten(row: dict, prefix: str = "") -> dict[str, float]:
    out: dict[str, float] = {}
    for key, value in row.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{name}."))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[_OLD_NAMES.get(name, name)] = float(value)
    return out


COMPARED = ("ms", "matmul_ms", "matmul_alone_s", "env_steps_per_s", "utilisation", "measured_over_limit", "peak_rss_mib", "cuda_max_allocated_mib",
            "matmul_gflops", "composed_s", "measured_s")


def compare(new: dict, old: dict) -> list[tuple[str, str, float, float]]:
    """(preset, metric, new, old) for every timing metric both results have."""
    old_rows = {r["preset"]: r for r in old.get("presets", [])}
    rows = []
    for r in new["presets"]:
        if r["preset"] not in old_rows:
            continue
        a, b = flatten(r), flatten(old_rows[r["preset"]])
        for key in a:
            if key in b and key.rsplit(".", 1)[-1] in COMPARED and b[key]:
                rows.append((r["preset"], key, a[key], b[key]))
    return rows


def print_comparison(rows: list[tuple[str, str, float, float]], old_path: str) -> None:
    print(f"\nnew / old ({old_path}); ms, s and MiB: below 1 is better; steps/s and utilisation: above 1")
    for preset, key, a, b in rows:
        print(f"  {preset:<14}{key:<42}{a:>12.3f}{b:>12.3f}{a / b:>8.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(DEFAULT_PRESETS))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--full-iteration", action="store_true", help="measure a real iteration on every preset")
    parser.add_argument("--measure-limit", type=float, default=60.0,
                        help="measure a real iteration when the composed one is shorter (seconds)")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: each preset's)")
    parser.add_argument("--set", nargs="*", metavar="KEY=VALUE", help="overrides for every preset")
    parser.add_argument("--json", default=None, help="also write the results to this file")
    parser.add_argument("--compare", default=None, metavar="OLD.json", help="print new/old ratios against it")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    kept = keep_freed_memory()  # as every drago run does

    print(f"torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}, "
          f"malloc keeps freed memory: {kept}")
    rows = [bench_preset(p, args) for p in args.presets]
    print_table(rows)
    result = {"threads": args.threads, "torch": torch.__version__, "overrides": args.set or [],
              "keep_freed_memory": kept, "presets": rows}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    if args.compare:
        print_comparison(compare(result, json.loads(Path(args.compare).read_text())), args.compare)


if __name__ == "__main__":
    main()
