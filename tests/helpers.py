"""Helpers shared by the test files (pytest puts this folder on the import path)."""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drago.agent.buffer import EpisodeReplay

#: How the tests start runs: no progress bar, no TensorBoard files.
QUIET = ["--no-progress", "train.tensorboard=false"]


def read_csv(path: Path) -> list[dict[str, str]]:
    with Path(path).open(newline="") as handle:
        return list(csv.DictReader(handle))


def filled_buffer(device_priorities: bool, obs_dim: int = 3, act_dim: int = 2, horizon: int = 3,
                  length: int = 20, episodes: int = 6) -> EpisodeReplay:
    """A CPU replay buffer of random episodes, its priorities in the host or the device form."""
    buf = EpisodeReplay(200, obs_dim, act_dim, horizon, length, device="cpu", device_priorities=device_priorities)
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        buf.add_episode(rng.random((length + 1, obs_dim)), rng.random((length, act_dim)), rng.random(length))
    return buf


def one_thread_env() -> dict[str, str]:
    """The environment of a subprocess run: this process's as it is now, with one thread, as the tests use."""
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


#: :func:`one_thread_env` of the environment the tests started with.
ONE_THREAD_ENV = one_thread_env()


def wait_for(predicate: Callable[[], bool], timeout: float, what: str, details: Callable[[], str] | None = None,
             interval: float = 0.5) -> None:
    """Polls ``predicate`` until it holds; TimeoutError naming ``what`` (and ``details()``) after ``timeout`` s.

    The suite's bounded wait: a predicate may also assert what must stay true meanwhile (a process still running).
    """
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return
        if time.monotonic() > deadline:
            extra = f"\n{details()}" if details else ""
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}{extra}")
        time.sleep(interval)


# ---------------------------------------------------------------------------------------------------
# Crash injection: how the tests stop a run in the middle. Inside the process, a call raises where a crash (or
# Ctrl-C) would stop it; from outside, a SIGKILL, which no handler sees.
# ---------------------------------------------------------------------------------------------------
class SimulatedCrash(RuntimeError):
    """What :func:`crash_at_call` raises by default: a test can tell it from an error of the code under test."""

    def __init__(self, message: str = "simulated crash"):
        super().__init__(message)


@contextlib.contextmanager
def crash_at_call(owner: Any, name: str, n: int = 1, when: Callable[..., bool] | None = None,
                  error: type[BaseException] = SimulatedCrash) -> Iterator[None]:
    """Make ``owner.name`` (a method of a class, or a function of a module) raise ``error`` at its ``n``-th call,
    counting only the calls whose arguments satisfy ``when`` (all of them without it); restored on exit.

    ``error=KeyboardInterrupt`` stands for Ctrl-C there. The code under test must look the name up at the call
    (``module.function(...)``, ``self.method(...)``), as it does for monkeypatching.
    """
    own = vars(owner).get(name)  # restored as it was: a subclass may inherit the name rather than define it
    original = getattr(owner, name)
    calls = 0

    def crashing(*args, **kwargs):
        nonlocal calls
        if when is None or when(*args, **kwargs):
            calls += 1
            if calls == n:
                raise error()
        return original(*args, **kwargs)

    setattr(owner, name, crashing)
    try:
        yield
    finally:
        if own is None:
            delattr(owner, name)
        else:
            setattr(owner, name, own)


def crash_at_gradient_step(method: type, n: int, task: int | str | None = None) -> contextlib.AbstractContextManager:
    """:func:`crash_at_call` at the ``n``-th ``method.gradient_step`` (of one task when ``task`` names it by index
    or name): a test then resumes the run and compares its logs with those of an uninterrupted one."""
    return crash_at_call(method, "gradient_step", n,
                         when=lambda self, state, *rest: task is None or task in (state.index, state.name))


def sigkill_in_task_two(train_args: list[str], run: Path, cwd: Path, wait_s: float = 300.0,
                        drago: Sequence[str] = (str(Path(sys.executable).parent / "drago"),)) -> int:
    """Start ``drago train *train_args --out run`` in a child process and SIGKILL it once a periodic checkpoint
    of task 2 exists; returns the child's exit status (``-SIGKILL`` when the kill landed).

    A periodic snapshot of task 2 is a ``resume.pt`` newer than task 1's checkpoint (task 1's own last
    snapshot exists for a moment next to ``task1_room1.pt`` before it is deleted). ``wait_s`` bounds the wait,
    generously for a loaded machine. ``drago`` is the command that starts drago (another environment's, say).
    The child gets this process's environment as it is at the call (a test's monkeypatched variables
    included), with one thread; its output goes to ``cwd / "train.log"``.
    """
    resume_ckpt, task1 = run / "checkpoints" / "resume.pt", run / "checkpoints" / "task1_room1.pt"
    log_path = cwd / "train.log"

    with log_path.open("w") as log:
        proc = subprocess.Popen([*drago, "train", *train_args, "--out", str(run)], stdout=log,
                                stderr=subprocess.STDOUT, env=one_thread_env(), cwd=cwd)

        def in_task2_with_checkpoint() -> bool:
            assert proc.poll() is None, (f"the run ended (rc {proc.returncode}) before it could be killed:\n"
                                         f"{log_path.read_text()[-2000:]}")
            try:
                return resume_ckpt.stat().st_mtime_ns > task1.stat().st_mtime_ns
            except FileNotFoundError:
                return False

        try:
            wait_for(in_task2_with_checkpoint, wait_s, "a periodic checkpoint in task 2", interval=0.02)
            proc.send_signal(signal.SIGKILL)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
    return proc.returncode


def tdmpc_config(**settings: Any):
    """An ``AgentConfig`` of kind tdmpc from flat keyword settings: the shared ones (lr, batch_size, ...) on the
    agent, every other one in its ``tdmpc`` section (``tdmpc_config(mlp_dim=64, lr=3e-4)``)."""
    from dataclasses import fields

    from drago.config import AgentConfig, TdmpcConfig

    shared = {f.name for f in fields(AgentConfig)}
    return AgentConfig(**{k: v for k, v in settings.items() if k in shared},
                       tdmpc=TdmpcConfig(**{k: v for k, v in settings.items() if k not in shared}))
