"""Every preset has a smoke path for each agent kind: ``drago train PRESET --smoke`` (docs: Getting started).

It keeps the preset's domain, tasks, agent kind and method and takes the smoke preset's budgets and sizes;
``benchmarks/smoke_paths.py`` prints how long each takes.
"""

from __future__ import annotations

import json

import pytest

import drago
from drago import cli
from drago.config import available_presets, load_config
from helpers import QUIET

SMOKE = load_config("smoke")


@pytest.mark.parametrize("preset", [p for p in available_presets() if p != "smoke"])
@pytest.mark.parametrize("kind", ["tdmpc", "pets"])
def test_every_preset_and_agent_kind_has_a_smoke_path(preset, kind):
    full = load_config(preset, [f"agent.kind={kind}"])
    cfg = load_config(preset, [f"agent.kind={kind}"], smoke=True)
    assert cfg.preset == f"{preset}+smoke"
    assert (cfg.env.domain, cfg.env.tasks, cfg.agent.kind) == (full.env.domain, full.env.tasks, kind)
    assert (cfg.train.steps_per_task, cfg.agent.seed_steps) == (SMOKE.train.steps_per_task, SMOKE.agent.seed_steps)
    assert (cfg.agent.tdmpc.mlp_dim, cfg.agent.pets.population) == (SMOKE.agent.tdmpc.mlp_dim, SMOKE.agent.pets.population)


def test_overrides_still_win_over_the_smoke_path():
    cfg = load_config("minigrid-cpu", ["train.steps_per_task=600"], smoke=True)
    assert cfg.train.steps_per_task == 600 and cfg.agent.tdmpc.mlp_dim == SMOKE.agent.tdmpc.mlp_dim


@pytest.mark.slow
def test_a_smoke_path_trains_the_preset_s_tasks(tmp_path):
    out = tmp_path / "run"
    assert cli.main(["train", "minigrid-pets-cpu", "--smoke", "env.tasks=[room1,room2]", "--out", str(out),
                     *QUIET]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [t["name"] for t in summary["tasks"]] == ["room1", "room2"]
    assert drago.load_config("smoke").train.steps_per_task == summary["tasks"][0]["steps"]
