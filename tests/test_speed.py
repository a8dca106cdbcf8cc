"""The speed settings' ``auto``: what it resolves to on which machine, and that a run records and keeps it."""

from __future__ import annotations

import pytest
import torch
import yaml
from helpers import tdmpc_config, QUIET

import drago.agent.speed as speed
from drago import cli
from drago.agent.agent import Agent
from drago.agent.networks import build_world_model
from drago.config import AgentConfig, ConfigError, load_config
from drago.envs import env_spec
from drago.training.rundir import config_diffs, read_run_config

CPU = torch.device("cpu")


@pytest.fixture
def machine(monkeypatch):
    """``machine(flags=..., compiler=...)`` makes this CPU look like one with those flags and a C++ compiler
    or none."""

    def make(flags: tuple[str, ...] = (), compiler: bool = True):
        monkeypatch.setattr(speed, "_cpu_flags", lambda: set(flags))
        monkeypatch.delenv("CXX", raising=False)
        monkeypatch.setattr(speed, "which", lambda name: f"/usr/bin/{name}" if compiler else None)
    return make


@pytest.mark.parametrize("flags, width, precision", [
    ((), 512, "float32"),                  # AVX2 only: no bfloat16 matmuls in hardware
    (("avx512_bf16",), 512, "bfloat16"),   # the paper's width on a CPU with AVX-512 BF16
    (("amx_bf16",), 1024, "bfloat16"),
    (("avx512_bf16",), 128, "float32"),    # too narrow to pay (it slowed planning at 128)
])
def test_auto_precision_chooses_bfloat16_only_for_fast_hardware_and_wide_networks(machine, flags, width, precision):
    machine(flags=flags)
    agent, notes = speed.resolve_agent_speed(tdmpc_config(mlp_dim=width), CPU)
    assert agent.tdmpc.precision == precision
    if flags and precision == "float32":
        assert notes == [f"agent.tdmpc.precision=auto chose float32: this CPU has {flags[0]}, but width {width} is under "
                         f"{speed.BFLOAT16_MIN_WIDTH}, where bfloat16 does not pay"]


def test_forced_settings_are_kept_as_they_are(machine):
    machine(flags=())
    agent, notes = speed.resolve_agent_speed(tdmpc_config(precision="bfloat16", compile="false", fast_tanh=False), CPU)
    assert (agent.tdmpc.precision, agent.tdmpc.compile, agent.tdmpc.fast_tanh, notes) == ("bfloat16", "false", False, [])


def test_auto_compile_compiles_where_a_compiler_exists_and_says_why_not_elsewhere(machine):
    machine(compiler=True)
    assert speed.resolve_agent_speed(AgentConfig(), CPU) == (tdmpc_config(precision="float32", compile="true"), [])
    machine(compiler=False)
    agent, notes = speed.resolve_agent_speed(AgentConfig(), CPU)
    assert agent.tdmpc.compile == "false"
    assert len(notes) == 1 and notes[0].startswith("agent.tdmpc.compile=auto runs eager: no C++ compiler (g++, c++, clang++)")
    with pytest.raises(ConfigError, match=r"^agent.tdmpc.compile=true cannot work here: no C\+\+ compiler .*; or set "
                                          r"agent.tdmpc.compile=false$"):
        speed.resolve_agent_speed(tdmpc_config(compile="true"), CPU)


def test_pets_resolves_to_float32_eager_and_refuses_the_others(machine):
    machine(flags=("avx512_bf16",), compiler=True)
    cfg = load_config("minigrid-pets-cpu", ["agent.pets.hidden=512"])
    agent, notes = speed.resolve_agent_speed(cfg.agent, CPU)
    assert (agent.tdmpc.precision, agent.tdmpc.compile, notes) == ("float32", "false", [])
    with pytest.raises(ConfigError, match="'agent.tdmpc.compile' applies to agent.kind=tdmpc"):
        load_config("minigrid-pets-cpu", ["agent.tdmpc.compile=true"])


def test_yaml_booleans_still_force_compile():
    assert load_config("smoke", ["agent.tdmpc.compile=true"]).agent.tdmpc.compile == "true"
    assert load_config("smoke", ["agent.tdmpc.compile=off"]).agent.tdmpc.compile == "false"
    with pytest.raises(ConfigError, match="unknown agent.tdmpc.compile 'sometimes'; valid choices: auto, true, false"):
        load_config("smoke", ["agent.tdmpc.compile=sometimes"])


def test_an_agent_built_outside_a_run_resolves_precision_and_stays_eager(machine):
    machine(flags=("avx512_bf16",), compiler=True)
    wm = build_world_model(load_config("smoke", ["agent.tdmpc.mlp_dim=512"]), env_spec("minigrid"))
    agent = Agent(wm, torch.optim.Adam(wm.dynamics.parameters()), tdmpc_config(mlp_dim=512), discrete=True)
    assert (agent.cfg.tdmpc.precision, agent.cfg.tdmpc.compile) == ("bfloat16", "false")


@pytest.mark.slow
def test_a_run_records_its_resolved_settings_prints_them_first_and_keeps_them_on_resume(machine, tmp_path, capsys):
    machine(compiler=False)
    out = tmp_path / "run"
    args = ["train", "smoke", "--method", "continual", "--out", str(out), *QUIET, "agent.tdmpc.compile=auto",
            "env.tasks=[room1]", "train.steps_per_task=200", "train.eval_freq=200"]
    assert cli.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"drago train smoke --method continual --seed 1 -> {out} (float32, eager, fast tanh)"
    assert lines[1].startswith("agent.tdmpc.compile=auto runs eager: no C++ compiler")
    written = yaml.safe_load((out / "config.yaml").read_text())["agent"]["tdmpc"]
    assert (written["precision"], written["compile"], written["fast_tanh"]) == ("float32", "false", True)
    # Another machine (a compiler, fast bfloat16) resumes the run with what it began with.
    machine(flags=("amx_bf16",), compiler=True)
    assert (read_run_config(out).agent.tdmpc.precision, read_run_config(out).agent.tdmpc.compile) == ("float32", "false")
    # A study asking for `auto` recognises the run as its own, whatever it resolved to.
    wanted = load_config("smoke", [a for a in args if "=" in a], method="continual", seed=1)
    assert config_diffs(read_run_config(out), wanted) == []
    assert config_diffs(read_run_config(out), load_config("smoke", ["agent.tdmpc.compile=true"])) != []


def test_a_run_written_before_the_auto_defaults_keeps_the_values_it_computed_with(tmp_path):
    cfg = load_config("smoke")
    data = cfg.to_dict()
    for key in ("precision", "compile", "fast_tanh"):
        del data["agent"]["tdmpc"][key]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    agent = read_run_config(tmp_path).agent
    assert (agent.tdmpc.precision, agent.tdmpc.compile, agent.tdmpc.fast_tanh) == ("float32", "false", False)
