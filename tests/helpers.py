"""Helpers shared by the test files (pytest puts this folder on the import path)."""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

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


def sigkill_in_task_two(train_args: list[str], run: Path, cwd: Path, wait_s: float = 300.0) -> int:
    """Start ``drago train *train_args --out run`` in a child process and SIGKILL it once a periodic checkpoint
    of task 2 exists; returns the child's exit status (``-SIGKILL`` when the kill landed).

    A periodic snapshot of task 2 is a ``resume.pt`` newer than task 1's checkpoint (task 1's own last
    snapshot exists for a moment next to ``task1_room1.pt`` before it is deleted). ``wait_s`` bounds the wait,
    generously for a loaded machine. The child gets this process's environment as it is at the call (a test's
    monkeypatched variables included), with one thread.
    """
    drago = Path(sys.executable).parent / "drago"
    resume_ckpt, task1 = run / "checkpoints" / "resume.pt", run / "checkpoints" / "task1_room1.pt"

    def in_task2_with_checkpoint() -> bool:
        try:
            return resume_ckpt.stat().st_mtime_ns > task1.stat().st_mtime_ns
        except FileNotFoundError:
            return False

    with (cwd / "train.log").open("w") as log:
        proc = subprocess.Popen([str(drago), "train", *train_args, "--out", str(run)], stdout=log,
                                stderr=subprocess.STDOUT, env=one_thread_env(), cwd=cwd)
        deadline = time.monotonic() + wait_s
        try:
            while not in_task2_with_checkpoint():
                assert proc.poll() is None, f"the run ended (rc {proc.returncode}) before it could be killed"
                assert time.monotonic() < deadline, f"no periodic checkpoint in task 2 within {wait_s:.0f} s"
                time.sleep(0.02)
            proc.send_signal(signal.SIGKILL)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
    return proc.returncode


@contextlib.contextmanager
def crash_at_gradient_step(method: type, n: int, task: int | str | None = None) -> Iterator[None]:
    """Make ``method.gradient_step`` raise ``RuntimeError("simulated crash")`` at its ``n``-th call (counting
    only the calls of one task when ``task`` names it by index or name), as a crash would stop a run there;
    restored on exit.

    The one crash injection of the suite: a test then resumes the run and compares its logs with those of an
    uninterrupted one.
    """
    original = method.gradient_step
    calls = {"n": 0}

    def crashing(self, state, u):
        if task is None or task in (state.index, state.name):
            calls["n"] += 1
            if calls["n"] == n:
                raise RuntimeError("simulated crash")
        return original(self, state, u)

    method.gradient_step = crashing
    try:
        yield
    finally:
        method.gradient_step = original
