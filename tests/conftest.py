"""Shared test settings and fixtures: one torch thread, so the suite stays light on a small shared CPU, and
smoke runs trained once per session."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from helpers import QUIET


@pytest.fixture(autouse=True)
def _one_torch_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def smoke_runs(tmp_path_factory) -> Callable[..., Path]:
    """``smoke_runs(method, *overrides)``: a finished run of the ``smoke`` preset, trained once per session
    for each distinct (method, overrides) and handed to each caller as a copy of its own, so a test may
    write into it (a transfer, a coverage file) without touching another test's run."""
    from drago import cli

    trained: dict[tuple[str, tuple[str, ...]], Path] = {}
    cache = tmp_path_factory.mktemp("smoke-runs")

    def get(method: str = "continual", *overrides: str) -> Path:
        key = (method, tuple(overrides))
        if key not in trained:
            out = cache / f"{method}-{len(trained)}"
            assert cli.main(["train", "smoke", "--method", method, "--out", str(out), *QUIET, *overrides]) == 0
            trained[key] = out
        copy = tmp_path_factory.mktemp(f"{method}-run") / "run"
        shutil.copytree(trained[key], copy)
        return copy

    return get
