"""The continual trainer: one task after another, the world model carried between them (paper §3.3, Algorithm 1; docs: Design, how a run flows).

Per iteration: one learner episode, the method's extra collection (DRAGO's reviewer), then
``updates_per_episode`` gradient iterations once past the seed phase; evaluation and periodic
checkpoints when their env-step period is crossed. A task ends with a final evaluation and a task
checkpoint, which is also how the next task receives the world model: a resumed run and an
uninterrupted one take exactly the same path.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from drago.agent.protocol import ContinualAgent
from drago.agent.buffer import EpisodeReplay, NonFinitePriority
from drago.agent.factory import build_agent, build_world_model, build_world_optimizer
from drago.config import Config
from drago.continual.base import Budget, ContinualMethod, TaskState, task_replay
from drago.envs import EnvSpec, make_env, task_optimum
from drago.seeding import rng_state, seeded_torch_rng, set_rng_state, task_seed
from drago.training.checkpoint import load_checkpoint, save_checkpoint
from drago.envs.episodes import EpisodeStart, run_episode, run_episodes
from drago.training.logger import RunLogger
from drago.training.resources import PeakMemory
from drago.training.rundir import resume_checkpoint_path, task_checkpoint_path, write_summary

class TrainingDiverged(RuntimeError):
    """A non-finite loss, gradient norm or weight; the message is one line naming where and how to go on."""


#: Starts an episode at a task step: ``start(env, task_step)`` returns the first observation.
TaskEpisodeStart = Callable[[Any, int], np.ndarray]
#: Called when task ``index`` is finished: ``hook(index, learner, step, buffers)`` with the task's final learner,
#: step counter and replay buffers by agent (``learner``, and what the method collected, e.g. ``reviewer``), or
#: ``(index, None, 0, {})`` for a task finished before this process started (a resumed run), which lets a
#: hook fill in what an older or crashed run lacks.
TaskEndHook = Callable[[int, "ContinualAgent | None", int, "dict[str, EpisodeReplay]"], None]
#: Extra blocks for ``summary.json``, given the summary's finished tasks.
SummaryExtras = Callable[[list[dict[str, Any]]], dict[str, Any]]

def completed_tasks(cfg: Config, run_dir: Path) -> int:
    """How many tasks of the sequence a run directory holds the checkpoints of, in order."""
    done = 0
    while done < len(cfg.env.tasks) and task_checkpoint_path(run_dir, cfg.env.tasks, done + 1).exists():
        done += 1
    return done


def global_env_step(cfg: Config, index: int, step: int = 0) -> int:
    """A monotone env step across the sequence for TensorBoard: task k starts at k * the most steps a task takes."""
    return (index * Budget.from_config(cfg).max_steps + step) * cfg.env.action_repeat


class Trainer:
    """Runs the configured task sequence into ``run_dir`` (:mod:`drago.training.run` builds one).

    The trainer knows nothing of the features built on it; it is handed what it calls:

    Args:
        episode_start: how learner and evaluation episodes start (None: a plain reset), e.g. a transfer's
            pre-rollout.
        task_end_hooks: called after each task's end, before its checkpoint (a crash in between redoes
            the end of the task and the hooks with it), e.g. recording the task's held-out set.
        summary_extras: extra blocks of ``summary.json``, e.g. a transfer's few-shot scores.
    """

    def __init__(self, cfg: Config, run_dir: Path, method: ContinualMethod, spec: EnvSpec, logger: RunLogger,
                 device: torch.device, progress: bool = True, episode_start: TaskEpisodeStart | None = None,
                 task_end_hooks: Sequence[TaskEndHook] = (), summary_extras: SummaryExtras | None = None):
        self.cfg = cfg
        self.run_dir = run_dir
        self.method = method
        self.spec = spec
        self.logger = logger
        self.device = device
        self.progress = progress
        self._episode_start = episode_start
        self.task_end_hooks = list(task_end_hooks)
        self.speed_notes: list[str] = []  # why an `auto` speed setting chose the slower path (drago.agent.speed)
        self.summary_extras = summary_extras
        self._eval_env_cache: tuple[str | None, list] = (None, [])

    # ---- paths and bookkeeping -------------------------------------------------------------
    def task_checkpoint(self, index: int) -> Path:
        return task_checkpoint_path(self.run_dir, self.cfg.env.tasks, index + 1)

    def start_checkpoint(self, index: int) -> Path | None:
        """The checkpoint task ``index`` starts from: the previous task's, or for the first task of a
        transfer run (``transfer.checkpoint``) the other run's stage it transfers from."""
        if index > 0:
            return self.task_checkpoint(index - 1)
        if self.cfg.transfer.checkpoint is not None:
            return self.run_dir / self.cfg.transfer.checkpoint  # an absolute path stays absolute
        return None

    @property
    def resume_checkpoint(self) -> Path:
        return resume_checkpoint_path(self.run_dir)

    def completed_tasks(self) -> int:
        return completed_tasks(self.cfg, self.run_dir)

    def env_steps(self, agent_steps: int) -> int:
        return agent_steps * self.cfg.env.action_repeat

    def global_env_step(self, task: TaskState | None = None, index: int = 0, step: int = 0) -> int:
        """A monotone step across the sequence for TensorBoard: task k starts at k * max task steps."""
        if task is not None:
            index, step = task.index, task.step
        return global_env_step(self.cfg, index, step)

    # ---- the sequence ----------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        """Train every task not yet finished, resuming a task in progress; returns the summary."""
        cfg = self.cfg
        start = self.completed_tasks()
        for index in range(start):
            self._task_finished(index)
        per_task = Budget.from_config(cfg).max_steps
        bar = tqdm(total=per_task * len(cfg.env.tasks), initial=start * per_task, unit="step", dynamic_ncols=True,
                   disable=None if self.progress else True, desc="drago")  # None: hide when not a terminal
        try:
            for index in range(start, len(cfg.env.tasks)):
                self.train_task(index, bar)
        finally:
            bar.close()
        summary = self.write_summary()
        self.logger.print(f"done: {self.run_dir} ({summary['wall_time_s']:.0f} s)")
        return summary

    def build_task(self, index: int) -> tuple[TaskState, dict[str, Any] | None]:
        """Everything task ``index`` starts with (paper §3.3; docs: Design, how a run flows), and the previous task's checkpoint.

        The world model comes from the previous task's checkpoint unless the method wants a fresh one;
        heads, optimizers, buffer and step counter are always new. Seeds depend only on (run seed,
        task), so a task rebuilt after a crash starts exactly as it did the first time.
        """
        cfg, spec, device = self.cfg, self.spec, self.device
        name = cfg.env.tasks[index]
        torch.manual_seed(task_seed(cfg.train.seed, index, 0))
        rng = np.random.default_rng(task_seed(cfg.train.seed, index, 1))
        env = make_env(cfg.env.domain, name, cfg.env.dense_reward, action_repeat=cfg.env.action_repeat)
        env.reset(seed=task_seed(cfg.train.seed, index, 2))

        world_model = build_world_model(cfg, spec, device)
        previous = None
        start = self.start_checkpoint(index)
        if start is not None:
            previous = load_checkpoint(start, kind="task", domain=cfg.env.domain, map_location=device)
            if not self.method.fresh_world_model:
                world_model.load_state_dict(previous["world_model"])
            self.method.load_carry_state(previous["method"])
        world_optimizer = build_world_optimizer(cfg, world_model)
        learner = build_agent(cfg, spec, world_model, world_optimizer, task=name)
        budget = Budget.from_config(cfg)
        buffer = task_replay(cfg, spec, budget.max_learner_steps, device)
        task = TaskState(index=index, name=name, world_model=world_model, world_optimizer=world_optimizer,
                         learner=learner, buffer=buffer, rng=rng, env=env, budget=budget,
                         schedule_clock=cfg.agent.schedule_clock)
        self.method.begin_task(task)
        return task, previous

    def train_task(self, index: int, bar: tqdm) -> None:
        cfg = self.cfg
        task, previous = self.build_task(index)
        name, env, buffer, learner, rng, budget = task.name, task.env, task.buffer, task.learner, task.rng, task.budget
        elapsed = cpu_elapsed = 0.0
        last_eval_env = last_ckpt_env = 0
        last_eval: dict[str, float] = {}
        memory = PeakMemory(self.device)
        memory.start()
        resumed = self._try_resume(task, env)
        if resumed is not None:
            elapsed, cpu_elapsed, last_eval_env, last_ckpt_env, last_eval = resumed
            bar.update(task.step)
            self.logger.print(f"[{name}] resumed at step {task.step} from {self.resume_checkpoint.name}")
        else:
            # Drop whatever a crashed attempt at this task had logged (a transfer's source run has logs of its own).
            self.logger.restore(previous["log_positions"] if index > 0 else {k: 0 for k in self.logger.positions()})
            last_eval = self.evaluate(task)
        started = time.perf_counter() - elapsed
        cpu_started = time.process_time() - cpu_elapsed

        seed_steps = cfg.agent.seed_steps
        L = cfg.env.episode_length
        while not budget.finished(task):
            t0, cpu0 = time.perf_counter(), time.process_time()
            step, schedule = task.step, task.schedule_step
            explore_randomly = step < seed_steps or len(buffer) < cfg.agent.batch_size

            def choose(obs, t, schedule=schedule, explore_randomly=explore_randomly):
                if explore_randomly:
                    return learner.random_action(rng)
                return learner.act(obs, schedule, eval_mode=False, first_step=t == 0)

            episode = run_episode(env, L, choose, self.episode_start(step))
            buffer.add_episode(episode.obs, episode.actions, episode.rewards)
            task.step += L
            task.learner_steps += L
            task.episodes += 1
            extra = self.method.collect(task)  # may add its own steps (DRAGO's reviewer episode)
            row: dict[str, Any] = {"task": name, "task_index": index, "episode": task.episodes, "step": task.step,
                                   "learner_step": task.learner_steps, "env_step": self.env_steps(task.step),
                                   "episode_reward": episode.ret, **extra}
            t1 = time.perf_counter()

            metrics: dict[str, torch.Tensor] = {}
            if step >= seed_steps:
                try:
                    for i in range(cfg.updates_per_episode):
                        metrics = self.method.gradient_step(task, schedule + i)
                except NonFinitePriority:
                    raise TrainingDiverged(self._divergence(task, "the replay priorities (TD errors) are not "
                                                                   "finite")) from None
            # Only the last gradient step is logged, as in the official code: one host sync per iteration.
            row.update({k: float(v) for k, v in metrics.items()})
            if metrics:
                self._check_finite(task, row, metrics)
            t2, cpu2 = time.perf_counter(), time.process_time()

            env_step = self.env_steps(task.step)
            global_step = self.global_env_step(task)
            self.logger.log("train", row, global_step)
            if self._eval_due(task, env_step, last_eval_env) or budget.finished(task):
                last_eval = self.evaluate(task)
                last_eval_env = env_step
            t3 = time.perf_counter()
            self.logger.log("timing", {"task": name, "episode": task.episodes, "env_step": env_step,
                                       "collect_s": round(t1 - t0, 4), "update_s": round(t2 - t1, 4),
                                       "eval_s": round(t3 - t2, 4), "cpu_s": round(cpu2 - cpu0, 4),
                                       "elapsed_s": round(time.perf_counter() - started, 2)}, global_step)
            bar.update(task.step - step)
            bar.set_postfix(task=name, ret=f"{episode.ret:.1f}", eval=f"{last_eval.get('episode_reward', 0):.1f}")
            if not budget.finished(task) and env_step // cfg.train.checkpoint_freq > last_ckpt_env // cfg.train.checkpoint_freq:
                last_ckpt_env = env_step
                self._save_resume(task, env, time.perf_counter() - started, time.process_time() - cpu_started,
                                  last_eval_env, last_ckpt_env, last_eval)

        # The bar counted each task at its largest budget; with separate budgets a task without a reviewer
        # (every task of `continual`, DRAGO's first) ends sooner, and the bar would stop short of its end.
        bar.total = max(bar.n, bar.total - (budget.max_steps - task.step))
        bar.refresh()
        buffers = {"learner": task.buffer, **self.method.collected_buffers(task)}
        self.method.end_task(task)
        self._task_finished(index, learner, task.step, buffers)
        wall = time.perf_counter() - started
        # Contention-free cost: CPU seconds of all threads, and this process's peak memory during the task.
        cost = {"cpu_time_s": time.process_time() - cpu_started, **memory.read()}
        save_checkpoint(self.task_checkpoint(index), {
            "task_index": index, "task": name, "config": cfg.to_dict(),
            "world_model": task.world_model.state_dict(),
            "method": self.method.carry_state(),
            # The learner is kept for pre-rollouts, held-out sets and the probes; chaining never reads it.
            **learner.task_state(),
            "final_eval": last_eval, "wall_time_s": wall, **cost, "steps": task.step, "learner_steps": task.learner_steps,
            "episodes": task.episodes, "log_positions": self.logger.positions(),
        }, kind="task", domain=cfg.env.domain)
        self.resume_checkpoint.unlink(missing_ok=True)
        self.logger.print(f"[{name}] finished: eval return {last_eval['episode_reward']:.1f}"
                          + (f" ({last_eval['fraction_of_optimal']:.0%} of optimal)" if "fraction_of_optimal" in last_eval else "")
                          + f", {task.episodes} episodes, {wall:.0f} s")
        self.write_summary()

    # ---- what the trainer is handed -------------------------------------------------------------
    def episode_start(self, step: int) -> EpisodeStart | None:
        """The ``start`` of learner and evaluation episodes at task step ``step`` (None: a plain reset)."""
        if self._episode_start is None:
            return None
        start = self._episode_start
        return lambda env: start(env, step)

    def _task_finished(self, index: int, learner: ContinualAgent | None = None, step: int = 0,
                       buffers: dict[str, EpisodeReplay] | None = None) -> None:
        for hook in self.task_end_hooks:
            hook(index, learner, step, buffers or {})

    # ---- evaluation --------------------------------------------------------------------------
    def _eval_due(self, task: TaskState, env_step: int, last_eval_env: int) -> bool:
        every = self.cfg.train.eval_every_episodes
        if every is not None:
            return task.episodes % every == 0
        return env_step // self.cfg.train.eval_freq > last_eval_env // self.cfg.train.eval_freq

    def evaluate(self, task: TaskState) -> dict[str, float]:
        """Mean undiscounted return of the learner's planner in eval mode on the current task.

        The ``eval_episodes`` episodes are played side by side, one batched plan per step, on a torch
        stream of their own: how often a run evaluates never changes what it learns.
        """
        cfg = self.cfg
        env_step = self.env_steps(task.step)
        envs = self._eval_envs(task)
        for episode, env in enumerate(envs):
            env.reset(seed=task_seed(cfg.train.seed, task.index, 3, env_step, episode))
        with seeded_torch_rng(task_seed(cfg.train.seed, task.index, 6, env_step), self.device):
            episodes = run_episodes(
                envs, cfg.env.episode_length,
                lambda obs, t: task.learner.act(obs, task.schedule_step, eval_mode=True, first_step=t == 0),
                self.episode_start(task.step))
        returns = [episode.ret for episode in episodes]
        result = {"episode_reward": float(np.mean(returns)), "episode_reward_std": float(np.std(returns))}
        optimum = task_optimum(cfg.env.domain, task.name, cfg.env.dense_reward)
        if optimum:
            result["optimal_return"] = optimum
            result["fraction_of_optimal"] = result["episode_reward"] / optimum
        # env_step counts every env step of the task (learner and reviewer); learner_env_step the learner's.
        row = {"task": task.name, "task_index": task.index, "step": task.step, "learner_step": task.learner_steps,
               "env_step": env_step, **result, "episode": task.episodes,
               "learner_env_step": self.env_steps(task.learner_steps)}
        self.logger.log("eval", row, self.global_env_step(task))
        self.logger.print(f"[{task.name}] env_step {env_step:>7d}  eval return {result['episode_reward']:7.1f}"
                          + (f"  ({result['fraction_of_optimal']:.0%} of optimal {optimum:.1f})" if optimum else ""))
        return result

    def _eval_envs(self, task: TaskState) -> list:
        """One env per evaluation episode, built once per task."""
        if self._eval_env_cache[0] != task.name:
            cfg = self.cfg
            self._eval_env_cache = (task.name, [
                make_env(cfg.env.domain, task.name, cfg.env.dense_reward, action_repeat=cfg.env.action_repeat)
                for _ in range(cfg.train.eval_episodes)])
        return self._eval_env_cache[1]

    # ---- divergence guard ----------------------------------------------------------------------
    def last_good_checkpoint(self, index: int) -> str:
        """What ``drago resume`` would continue task ``index`` from, for the divergence message."""
        if self.resume_checkpoint.exists():
            return str(self.resume_checkpoint)
        start = self.start_checkpoint(index)
        return f"{start} (the task restarts)" if start is not None else "none yet (the task restarts from its beginning)"

    def _check_finite(self, task: TaskState, row: dict[str, Any], metrics: dict[str, torch.Tensor]) -> None:
        """Stop the run at the first non-finite loss, gradient norm or network weight (one line, naming the
        task, the step, the quantity and the last good checkpoint); checkpoints are checked on save too."""
        bad = next((k for k in metrics if not math.isfinite(row[k])), None)
        if bad is None:
            named = [("world model", task.world_model), *task.learner.trained_modules().items()]
            finite = torch.stack([torch.isfinite(p).all() for _, module in named for p in module.parameters()])
            if not bool(finite.all()):
                bad = next(name for name, module in named
                           if not all(bool(torch.isfinite(p).all()) for p in module.parameters()))
                raise TrainingDiverged(self._divergence(task, f"a weight of the {bad} is not finite"))
            return
        raise TrainingDiverged(self._divergence(task, f"{bad} is {row[bad]}"))

    def _divergence(self, task: TaskState, what: str) -> str:
        return (f"[{task.name}] training diverged at task step {task.step} (env step {self.env_steps(task.step)}): "
                f"{what}; the last good checkpoint is {self.last_good_checkpoint(task.index)}; "
                f"`drago resume {self.run_dir}` continues from it (with the same settings it may diverge again: "
                "see docs: Speed and precision)")

    # ---- resumable snapshots -------------------------------------------------------------------
    def _save_resume(self, task: TaskState, env, elapsed: float, cpu_elapsed: float, last_eval_env: int,
                     last_ckpt_env: int, last_eval: dict[str, float]) -> None:
        save_checkpoint(self.resume_checkpoint, {
            "task_index": task.index, "step": task.step, "learner_steps": task.learner_steps,
            "episodes": task.episodes, "world_model": task.world_model.state_dict(),
            "world_optimizer": task.world_optimizer.state_dict(), "learner": task.learner.state_dict(),
            "buffer": task.buffer.state_dict(), "method_task": self.method.task_state_dict(task),
            "rng": rng_state(task.rng), "env_rng": rng_state(env.np_random), "torch_rng": torch.get_rng_state(),
            "elapsed": elapsed, "cpu_elapsed": cpu_elapsed, "last_eval_env": last_eval_env, "last_ckpt_env": last_ckpt_env,
            "last_eval": last_eval, "log_positions": self.logger.positions(),
        }, kind="resume", domain=self.cfg.env.domain)

    def _try_resume(self, task: TaskState, env) -> tuple[float, float, int, int, dict[str, float]] | None:
        if not self.resume_checkpoint.exists():
            return None
        state = load_checkpoint(self.resume_checkpoint, kind="resume", domain=self.cfg.env.domain,
                                map_location=self.device)
        if state["task_index"] != task.index:
            return None
        task.world_model.load_state_dict(state["world_model"])
        task.world_optimizer.load_state_dict(state["world_optimizer"])
        task.learner.load_state_dict(state["learner"])
        task.buffer.load_state_dict(state["buffer"])
        self.method.load_task_state_dict(task, state["method_task"])
        set_rng_state(task.rng, state["rng"])
        set_rng_state(env.np_random, state["env_rng"])
        torch.set_rng_state(state["torch_rng"])
        task.step, task.learner_steps, task.episodes = state["step"], state["learner_steps"], state["episodes"]
        self.logger.restore(state["log_positions"])
        return (state["elapsed"], state.get("cpu_elapsed", 0.0), state["last_eval_env"], state["last_ckpt_env"],
                state["last_eval"])

    # ---- summary -------------------------------------------------------------------------------
    def write_summary(self) -> dict[str, Any]:
        cfg = self.cfg
        tasks = []
        for index, name in enumerate(cfg.env.tasks):
            path = self.task_checkpoint(index)
            if not path.exists():
                continue
            data = load_checkpoint(path, kind="task", domain=cfg.env.domain)
            final = data["final_eval"]
            tasks.append({"index": index, "name": name, "final_eval_return": final["episode_reward"],
                          "final_eval_return_std": final["episode_reward_std"],
                          "optimal_return": final.get("optimal_return"),
                          "fraction_of_optimal": final.get("fraction_of_optimal"),
                          "steps": data["steps"], "learner_steps": data["learner_steps"],
                          "env_steps": self.env_steps(data["steps"]), "episodes": data["episodes"],
                          "wall_time_s": round(data["wall_time_s"], 2),
                          # Absent from checkpoints written before these were recorded.
                          "cpu_time_s": round(data["cpu_time_s"], 2) if "cpu_time_s" in data else None,
                          "peak_rss_mib": round(data["peak_rss_mib"], 1) if "peak_rss_mib" in data else None,
                          "checkpoint": str(path.relative_to(self.run_dir))})
        summary = {"preset": cfg.preset, "method": cfg.method.name, "seed": cfg.train.seed, "domain": cfg.env.domain,
                   "tasks_planned": list(cfg.env.tasks), "complete": len(tasks) == len(cfg.env.tasks),
                   "tasks": tasks, "wall_time_s": round(sum(t["wall_time_s"] for t in tasks), 2)}
        if self.summary_extras is not None:
            summary.update(self.summary_extras(tasks))
        write_summary(self.run_dir, summary)
        return summary
