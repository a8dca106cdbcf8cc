"""Shared test settings and fixtures: one torch thread, so the suite stays light on a small shared CPU, and
smoke runs trained once per session."""

from __future__ import annotations

import fcntl
import hashlib
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from helpers import QUIET


# The files that take longest, longest first. Under pytest-xdist (``--dist loadfile``) each file goes whole to
# one worker, in collection order: starting the long ones first lets the short ones fill in at the end,
# instead of one worker finishing a long file alone while the other waits.
LONG_FILES = ("test_records.py", "test_study_slurm.py", "test_study.py", "test_trainer.py", "test_transfer.py",
              "test_drago.py", "test_report.py", "test_agent.py")


@pytest.hookimpl(tryfirst=True)  # before pytest deselects by marker, so that the marker added here counts
def pytest_collection_modifyitems(config, items):
    """Long files first (see :data:`LONG_FILES`); every ``experiment`` test is also ``slow``; tests marked
    ``cuda`` run where torch sees a CUDA GPU and are skipped, with the reason, elsewhere."""
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))  # stable: the rest keep their order
    # A command line's -m replaces the one in addopts: without this, `-m "not slow"` would run the experiments.
    for item in items:
        if item.get_closest_marker("experiment"):
            item.add_marker(pytest.mark.slow)
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (torch.cuda.is_available() is False); "
                                   "benchmarks/gpu_check.sh runs these on a GPU machine")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session", autouse=True)
def _one_torch_thread_for_fixtures():
    """Module and session fixtures are set up before any function fixture, and some of them train: with every
    core's thread on a machine already busy, one of them took ten times as long."""
    torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def smoke_runs(tmp_path_factory, request) -> Callable[..., Path]:
    """``smoke_runs(method, *overrides)``: a finished run of the ``smoke`` preset, trained once per suite
    for each distinct (method, overrides) and handed to each caller as a copy of its own, so a test may
    write into it (a transfer, a coverage file) without touching another test's run.

    Under pytest-xdist the workers share one cache beside their own temporary folders: the first worker to
    ask for a run trains it under a file lock, the others wait for it and copy it.
    """
    from drago import cli

    base = tmp_path_factory.getbasetemp()
    shared = hasattr(request.config, "workerinput")  # an xdist worker: its folder is one of several
    cache = (base.parent if shared else base) / "smoke-runs"
    cache.mkdir(exist_ok=True)

    def get(method: str = "continual", *overrides: str) -> Path:
        key = hashlib.sha1("\0".join((method, *overrides)).encode()).hexdigest()[:12]
        out = cache / f"{method}-{key}"
        with (cache / f"{method}-{key}.lock").open("w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not out.exists():
                partial = cache / f"{method}-{key}.partial"
                shutil.rmtree(partial, ignore_errors=True)
                assert cli.main(["train", "smoke", "--method", method, "--out", str(partial), *QUIET,
                                 *overrides]) == 0
                partial.rename(out)
        copy = tmp_path_factory.mktemp(f"{method}-run") / "run"
        shutil.copytree(out, copy)
        return copy

    return get
