"""Config loading, overrides and the `drago` command's error handling (one line, exit code 2)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from drago import cli
from drago.config import Config, ConfigError, available_presets, describe_settings, load_config
from drago.continual import METHODS
from drago.envs import GRID_TASKS
from helpers import crash_at_call


# ---------------------------------------------------------------------------------------------------
# Presets and overrides
# ---------------------------------------------------------------------------------------------------
def test_presets_are_listed():
    assert {"smoke", "minigrid", "minigrid-cpu"} <= set(available_presets())


def test_load_smoke_preset_layers_on_its_bases():
    cfg = load_config("smoke")
    assert cfg.preset == "smoke"
    # From smoke.yaml itself.
    assert (cfg.agent.tdmpc.mlp_dim, cfg.agent.tdmpc.horizon, cfg.agent.batch_size) == (32, 3, 32)
    assert (cfg.train.steps_per_task, cfg.train.checkpoint_freq, cfg.train.threads) == (400, 200, 1)
    # Inherited from minigrid-cpu (not overridden by smoke) and from minigrid.
    assert (cfg.agent.tdmpc.elite_selection, cfg.agent.tdmpc.temperature, cfg.agent.tdmpc.lr_final) == ("sample", 2.0, 1e-4)
    assert cfg.agent.tdmpc.lr_schedule_steps == cfg.train.steps_per_task == 400
    assert cfg.env.tasks == ("room1", "room2", "room3", "room4")
    assert cfg.env.episode_length == 100
    # Untouched defaults (paper Appendix A.1).
    assert (cfg.agent.tdmpc.rho, cfg.agent.tdmpc.tau, cfg.agent.tdmpc.discount) == (0.5, 0.01, 0.99)
    assert cfg.method.name == "continual"


def test_minigrid_preset_is_the_paper_values():
    cfg = load_config("minigrid")
    a, t = cfg.agent, cfg.agent.tdmpc
    assert (t.mlp_dim, t.horizon, a.batch_size, t.iterations, t.num_samples, t.num_elites) == (512, 10, 512, 6, 512, 64)
    assert (t.update_freq, a.seed_steps, t.horizon_schedule_steps) == (40, 5000, 10_000)
    assert cfg.train.steps_per_task == 300_000


def test_dotted_and_short_overrides_with_type_conversion():
    cfg = load_config("smoke", [
        "agent.tdmpc.mlp_dim=64",  # dotted int
        "lr=0.01",  # unique short key, float
        "use_crelu=false",  # bool
        "env.tasks=[room2, room1]",  # tuple from a YAML list
        "random_action_probs=[0.1, 0.1, 0.8]",  # tuple of floats from a YAML list
        "train.updates_per_episode=null",  # None for an optional int
        "dense_reward=None",
        "discount=1",  # an int where a float is declared
        "steps_per_task=1000",
        "tensorboard=true",
    ])
    assert cfg.agent.tdmpc.mlp_dim == 64 and isinstance(cfg.agent.tdmpc.mlp_dim, int)
    assert cfg.agent.lr == 0.01
    assert cfg.agent.tdmpc.use_crelu is False
    assert cfg.env.tasks == ("room2", "room1")
    assert cfg.agent.random_action_probs == (0.1, 0.1, 0.8)
    assert cfg.train.updates_per_episode is None
    assert cfg.env.dense_reward is None
    assert cfg.agent.tdmpc.discount == 1.0 and isinstance(cfg.agent.tdmpc.discount, float)
    assert cfg.train.steps_per_task == 1000
    assert cfg.train.tensorboard is True
    assert cfg.updates_per_episode == cfg.env.episode_length  # None means one update per agent step


@pytest.mark.parametrize("raw", ["(0.1,0.1,0.8)", "0.1,0.1,0.8"])
def test_numeric_tuple_override_from_plain_string(raw):
    cfg = load_config("smoke", [f"agent.random_action_probs={raw}"])
    assert cfg.agent.random_action_probs == (0.1, 0.1, 0.8)


@pytest.mark.parametrize("raw, expected", [("3e-4", 3e-4), ("1E-3", 1e-3), ("+2.5e+1", 25.0), (".5e1", 5.0)])
def test_exponent_without_dot_is_a_number(raw, expected):
    # YAML 1.1 alone reads "3e-4" as a string.
    assert load_config("smoke", [f"agent.lr={raw}"]).agent.lr == pytest.approx(expected)


def test_string_tuple_override_from_plain_string():
    assert load_config("smoke", ["env.tasks=room2,room1"]).env.tasks == ("room2", "room1")
    assert load_config("smoke", ["env.tasks=(room3, room4)"]).env.tasks == ("room3", "room4")


def test_method_and_seed_shortcuts():
    cfg = load_config("smoke", method="scratch", seed=7)
    assert cfg.method.name == "scratch" and cfg.train.seed == 7


def test_round_trip_through_dict_and_yaml():
    cfg = load_config("smoke", ["agent.tdmpc.mlp_dim=24", "env.tasks=[room3,room1]", "train.seed=5",
                                "env.dense_reward=false"])
    assert Config.from_dict(cfg.to_dict()) == cfg
    assert Config.from_dict(yaml.safe_load(yaml.safe_dump(cfg.to_dict()))) == cfg


@pytest.mark.parametrize("override", ["agent.tdmpc.mlp_dim=abc", "agent.tdmpc.use_crelu=maybe", "agent.foo=1", "foo=1",
                                      "model.mlp_dim=3", "agent.tdmpc.rho=1.5", "agent.tdmpc.horizon=0",
                                      "agent.random_action_probs=[0.5,0.5,0.5]", "train.device=tpu",
                                      "env.episode_length=3", "mlp_dim"])
def test_bad_overrides_raise_one_line_config_error(override):
    with pytest.raises(ConfigError) as info:
        load_config("smoke", [override])
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------------
# The command line: every user error is one line on stderr and exit code 2
# ---------------------------------------------------------------------------------------------------
def _existing_run(tmp: Path) -> Path:
    run = tmp / "existing"
    run.mkdir()
    (run / "config.yaml").write_text(yaml.safe_dump(load_config("smoke").to_dict(), sort_keys=False))
    return run


def _corrupt_task_checkpoint(tmp: Path) -> Path:
    run = _existing_run(tmp)
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "task1_room1.pt").write_bytes(b"\x00garbage, not a checkpoint\xff" * 10)
    return run


def _not_a_run(tmp: Path) -> Path:
    run = tmp / "stuff"
    run.mkdir()
    (run / "notes.txt").write_text("keep me")
    return run


OUT = "--out={tmp}/run"  # every `train` call gets its own --out, so nothing can write under runs/

BAD_INVOCATIONS = {
    "unknown-preset": ["train", "nope", OUT],
    "unknown-method": ["train", "smoke", "--method", "nope", OUT],
    "unknown-task": ["train", "smoke", "env.tasks=[room9]", OUT],
    "unknown-short-key": ["train", "smoke", "foo=1", OUT],
    "unknown-dotted-key": ["train", "smoke", "agent.foo=1", OUT],
    "unknown-section": ["train", "smoke", "model.mlp_dim=3", OUT],
    "int-not-a-number": ["train", "smoke", "agent.tdmpc.mlp_dim=abc", OUT],
    "bool-maybe": ["train", "smoke", "agent.tdmpc.use_crelu=maybe", OUT],
    "zero-budget": ["train", "smoke", "train.steps_per_task=0", OUT],
    "negative-batch": ["train", "smoke", "agent.batch_size=-1", OUT],
    "elites-exceed-samples": ["train", "smoke", "agent.tdmpc.num_elites=100", "agent.tdmpc.num_samples=10", OUT],
    "rho-out-of-range": ["train", "smoke", "agent.tdmpc.rho=1.5", OUT],
    "episode-shorter-than-horizon": ["train", "smoke", "env.episode_length=2", OUT],
    "unknown-device": ["train", "smoke", "train.device=tpu", OUT],
    "rehearsal-weight-without-joint": ["train", "smoke", "--method", "drago", "method.rehearsal.weight=0", OUT],
    "negative-seed": ["train", "smoke", "--seed", "-1", OUT],
    "override-without-equals": ["train", "smoke", "mlp_dim", OUT],
    "unknown-option": ["train", "smoke", "--bogus", OUT],
    "existing-run-dir": ["train", "smoke", "--out={existing}"],
    "force-on-foreign-dir": ["train", "smoke", "--force", "--out={foreign}"],
    "resume-missing-dir": ["resume", "{tmp}/does-not-exist", "--no-progress"],
    "resume-not-a-run": ["resume", "{foreign}", "--no-progress"],
    "resume-corrupt-checkpoint": ["resume", "{corrupt}", "--no-progress"],
    "unknown-subcommand": ["frobnicate"],
    "no-subcommand": [],
    "missing-preset": ["train"],
    "list-extra-argument": ["list", "extra"],
    "cuda-unavailable": ["train", "smoke", "train.device=cuda", OUT],
    "allocator-env-maybe": ["train", "smoke", OUT],  # with DRAGO_KEEP_FREED_MEMORY=maybe
    "study-allocator-env-maybe": ["study", "smoke", "--out", "{tmp}/study"],  # the same
}

#: What each message must name.
NAMED_IN_THE_MESSAGE = {
    "unknown-preset": "nope", "unknown-method": "nope", "unknown-task": "room9", "unknown-short-key": "foo",
    "unknown-dotted-key": "agent.foo", "unknown-section": "model", "int-not-a-number": "agent.tdmpc.mlp_dim",
    "bool-maybe": "agent.tdmpc.use_crelu", "zero-budget": "train.steps_per_task", "negative-batch": "agent.batch_size",
    "elites-exceed-samples": "num_elites", "rho-out-of-range": "agent.tdmpc.rho", "unknown-device": "tpu",
    "override-without-equals": "mlp_dim", "unknown-option": "--bogus", "existing-run-dir": "--force",
    "resume-missing-dir": "does-not-exist", "resume-corrupt-checkpoint": "task1_room1.pt",
    "unknown-subcommand": "frobnicate", "cuda-unavailable": "cuda", "allocator-env-maybe": "DRAGO_KEEP_FREED_MEMORY",
    "study-allocator-env-maybe": "DRAGO_KEEP_FREED_MEMORY", "episode-shorter-than-horizon": "env.episode_length",
    "negative-seed": "--seed", "rehearsal-weight-without-joint": "method.rehearsal.mode=joint",
    "force-on-foreign-dir": "not a drago run", "resume-not-a-run": "not a drago run",
    "no-subcommand": "COMMAND", "missing-preset": "preset", "list-extra-argument": "extra",
}


@pytest.mark.parametrize("argv", list(BAD_INVOCATIONS.values()), ids=list(BAD_INVOCATIONS))
def test_bad_invocation_is_one_line_and_exit_2(argv, tmp_path, capsys, monkeypatch, request):
    name = request.node.callspec.id
    if name == "cuda-unavailable" and torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    monkeypatch.chdir(tmp_path)  # a default run directory would land in tmp_path, never in the repo
    if name in ("allocator-env-maybe", "study-allocator-env-maybe"):
        monkeypatch.setenv("DRAGO_KEEP_FREED_MEMORY", "maybe")
    places = {"tmp": tmp_path}
    if any("{existing}" in a for a in argv):
        places["existing"] = _existing_run(tmp_path)
    if any("{foreign}" in a for a in argv):
        places["foreign"] = _not_a_run(tmp_path)
    if any("{corrupt}" in a for a in argv):
        places["corrupt"] = _corrupt_task_checkpoint(tmp_path)
    args = [a.format(**places) for a in argv]

    code = cli.main(args)
    err = capsys.readouterr().err
    print(f"{name}: {err.rstrip()}")
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{err}"
    assert lines[0].startswith("drago: error: ")
    assert "Traceback" not in err
    assert NAMED_IN_THE_MESSAGE[name] in lines[0]
    assert not (tmp_path / "run").exists() or name in ("existing-run-dir",)
    if "foreign" in places:
        assert (places["foreign"] / "notes.txt").read_text() == "keep me"  # never deleted


def test_resume_corrupt_checkpoint_with_progress_bar_is_one_line(tmp_path, capsys):
    run = _corrupt_task_checkpoint(tmp_path)
    assert cli.main(["resume", str(run)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1, lines


def test_missing_preset_message_does_not_require_overrides(capsys):
    assert cli.main(["train"]) == 2
    assert "key=value" not in capsys.readouterr().err


def test_bad_config_writes_no_run_dir(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli.main(["train", "smoke", "agent.tdmpc.mlp_dim=abc", "--out", str(out)]) == 2
    assert not out.exists()


# ---------------------------------------------------------------------------------------------------
# drago list
# ---------------------------------------------------------------------------------------------------
def test_list_mentions_every_preset_method_and_task(capsys):
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    for name in [*available_presets(), *METHODS, *GRID_TASKS]:
        assert name in out, name
    # Every domain's tasks, each on its own line with its description, and the sequences.
    lines = out.splitlines()
    for name in ("cheetah-jump-and-run-backwards", "cheetah-run", "walker-walk-backwards", "walker-stand"):
        assert any(line.split()[:1] == [name] and len(line.split()) > 1 for line in lines), name
    assert "walker-run -> walker-walk -> walker-walk-backwards -> walker-stand" in out
    assert "room1 -> room2 -> room3 -> room4" in out


def test_list_settings_mentions_every_setting(capsys):
    assert cli.main(["list", "--settings"]) == 0
    out = capsys.readouterr().out
    for name in [*available_presets(), *METHODS, *GRID_TASKS]:
        assert name in out, name
    keys = [key for key, _, _ in describe_settings()]
    assert "agent.tdmpc.mlp_dim" in keys and "train.steps_per_task" in keys
    for key in keys:
        assert key in out, key


def test_interrupted_train_and_resume_name_the_run_to_continue(tmp_path, capsys):
    from drago.training.trainer import Trainer

    out = tmp_path / "run"
    with crash_at_call(Trainer, "run", error=KeyboardInterrupt):  # Ctrl-C as the sequence starts
        assert cli.main(["train", "smoke", "--out", str(out), "--no-progress"]) == 130
    assert capsys.readouterr().err.strip() == f"drago: interrupted; continue with `drago resume {out}`"
    with crash_at_call(Trainer, "run", error=KeyboardInterrupt):
        assert cli.main(["resume", str(out), "--no-progress"]) == 130
    assert capsys.readouterr().err.strip() == f"drago: interrupted; continue with `drago resume {out}`"


@pytest.mark.parametrize("force", [False, True])
def test_interrupted_paper_cases_say_how_to_continue(force, tmp_path, capsys):
    from drago import api

    argv = ["transfer", str(tmp_path), "--paper-cases", *(["--force"] if force else [])]
    with crash_at_call(api, "run_paper_cases", error=KeyboardInterrupt):
        assert cli.main(argv) == 130
    again = "again without --force" if force else "again"
    assert capsys.readouterr().err.strip() == (
        f"drago: interrupted; run the same `drago transfer --paper-cases` command {again} to continue")
