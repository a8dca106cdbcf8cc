"""The public Python API (docs: Extending drago): preset files, the method registry and its plug-ins, Run."""

from __future__ import annotations

import importlib.metadata
import sys
import textwrap

import numpy as np
import pytest

import drago
from drago import api
from drago.config import ConfigError
from drago.continual import Continual, registry


# ---------------------------------------------------------------------------------------------------
# Presets from a file
# ---------------------------------------------------------------------------------------------------
def write(path, text: str):
    path.write_text(textwrap.dedent(text).lstrip())
    return path


def test_a_preset_file_builds_on_a_packaged_preset(tmp_path):
    path = write(tmp_path / "mine.yaml", """
        # two rooms of the smoke preset, a wider network
        base: smoke
        env:
          tasks: [room1, room2]
        agent:
          tdmpc:
            mlp_dim: 48
        """)
    cfg = api.load_config(str(path), ["train.seed=3"], method="drago")
    smoke = api.load_config("smoke")
    assert (cfg.preset, cfg.env.tasks, cfg.agent.tdmpc.mlp_dim, cfg.train.seed, cfg.method.name) == (
        "mine", ("room1", "room2"), 48, 3, "drago")
    assert cfg.agent.tdmpc.horizon == smoke.agent.tdmpc.horizon and cfg.train.steps_per_task == smoke.train.steps_per_task


def test_a_preset_file_may_build_on_another_file(tmp_path):
    write(tmp_path / "base.yaml", "base: smoke\nagent:\n  tdmpc:\n    mlp_dim: 24\n")
    top = write(tmp_path / "top.yaml", "base: base.yaml\nagent:\n  tdmpc:\n    horizon: 2\n")
    cfg = api.load_config(str(top))
    assert (cfg.agent.tdmpc.mlp_dim, cfg.agent.tdmpc.horizon) == (24, 2)


@pytest.mark.parametrize("text, expected", [
    ("base: smoke\nagent:\n  tdmpc:\n    mlp_dim: 16\n    horizn: 3\n", ":5: unknown setting 'agent.tdmpc.horizn'"),
    ("base: smoke\nagent:\n  seed_steps: 10\n  pets_horizon: 3\n",
     ":4: setting 'agent.pets_horizon' was renamed; write agent.pets.horizon"),
    ("base: smoke\ntrain:\n  steps_per_task: lots\n", ":3: setting 'train.steps_per_task' expects an integer"),
    ("base: smoke\nagnet:\n  mlp_dim: 16\n", ":2: unknown section 'agnet'"),
    ("agent:\n  mlp_dim: [1\n", ":3: not valid YAML"),
    ("base: nope\n", "unknown preset 'nope'"),
    ("base: loop.yaml\n", "base chain loops"),
    ("- a list\n", "a preset must be a mapping"),
])
def test_a_bad_preset_file_names_the_file_and_line(tmp_path, text, expected):
    path = write(tmp_path / "loop.yaml", text)
    with pytest.raises(ConfigError) as err:
        api.load_config(str(path))
    message = str(err.value)
    assert expected in message and len(message.splitlines()) == 1
    if expected.startswith(":"):
        assert message.startswith(f"{path}{expected}")


def test_a_missing_preset_file_says_what_to_give(tmp_path):
    with pytest.raises(ConfigError, match="does not exist; give a path to a YAML file or a packaged preset"):
        api.load_config(str(tmp_path / "missing.yaml"))


# ---------------------------------------------------------------------------------------------------
# The method registry
# ---------------------------------------------------------------------------------------------------
@pytest.fixture
def clean_registry(monkeypatch):
    """The registry as it is, restored after the test (methods and plug-in state)."""
    monkeypatch.setattr(registry, "METHODS", dict(registry.METHODS))
    monkeypatch.setattr(registry, "_problems", [])
    monkeypatch.setattr(registry, "_plugins_loaded", True)
    return registry


def test_a_registered_method_trains_like_a_built_in_one(clean_registry, tmp_path):
    # Through the top-level names, as the docs show them: drago.train is the API's function, not a subpackage.
    @drago.register_method("reset-nothing")
    class ResetNothing(Continual):
        description = "continual TD-MPC under another name"

    assert "reset-nothing" in drago.available_methods() and drago.methods()["reset-nothing"] is ResetNothing
    cfg = drago.load_config("smoke", ["env.tasks=[room1]", "train.steps_per_task=200"], method="reset-nothing")
    run = drago.train(cfg, out=tmp_path / "run", progress=False)
    assert isinstance(run, drago.Run) and run.complete and run.config.method.name == "reset-nothing"


@pytest.mark.parametrize("name, cls, expected", [
    ("drago", Continual, "method 'drago' is already registered by drago.continual.drago.Drago; choose another name"),
    ("not-a-method", dict, "is not a subclass of drago.ContinualMethod"),
    ("Bad Name", Continual, "must be lowercase letters, digits"),
])
def test_wrong_registrations_say_what_to_fix(clean_registry, name, cls, expected):
    with pytest.raises(api.RegistryError) as err:
        api.register_method(name, cls)
    assert expected in str(err.value) and len(str(err.value).splitlines()) == 1


def test_an_unknown_method_lists_the_registered_ones():
    with pytest.raises(ConfigError, match=r"unknown method 'nope'; valid methods: continual, scratch, drago"):
        api.load_config("smoke", method="nope")


def fake_distribution(root, name: str, entry_points: str, modules: dict[str, str]):
    """An installed package on ``root``: its dist-info (with entry points) and its modules."""
    info = root / f"{name.replace('-', '_')}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(entry_points).lstrip())
    for module, source in modules.items():
        (root / f"{module}.py").write_text(textwrap.dedent(source).lstrip())


def test_plugins_load_from_entry_points_and_a_broken_one_is_skipped_with_one_line(
        clean_registry, tmp_path, monkeypatch, capsys):
    fake_distribution(tmp_path, "drago-good-plugin", """
        [drago.methods]
        good-method = good_plugin:GoodMethod
        """, {"good_plugin": """
        from drago.continual import Continual

        class GoodMethod(Continual):
            description = "a plug-in method"
        """})
    fake_distribution(tmp_path, "drago-broken-plugin", """
        [drago.methods]
        broken-method = broken_plugin:Broken
        """, {"broken_plugin": "import a_module_that_does_not_exist\n"})
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "_plugins_loaded", False)
    importlib.invalidate_caches()
    found = registry.methods()
    assert "good-method" in found and "broken-method" not in found and "drago" in found
    warning = capsys.readouterr().err.strip()
    assert len(warning.splitlines()) == 1
    # One format for every kind of plug-in (drago.plugins), the same as the domain registry's.
    assert warning == ("drago: warning: method plug-in 'broken-method = broken_plugin:Broken' of package "
                       "'drago-broken-plugin' skipped: ModuleNotFoundError: No module named "
                       "'a_module_that_does_not_exist'")
    assert [str(p) for p in registry.plugin_problems()] == [warning.removeprefix("drago: warning: ")]
    registry.methods()  # loaded once: no second warning
    assert capsys.readouterr().err == ""
    for module in ("good_plugin", "broken_plugin"):
        sys.modules.pop(module, None)


def test_the_fake_distribution_is_what_entry_points_see(tmp_path, monkeypatch):
    fake_distribution(tmp_path, "drago-probe", "[drago.methods]\nprobe = probe_plugin:X\n", {"probe_plugin": "X = 1\n"})
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    probe = [e for e in importlib.metadata.entry_points(group="drago.methods") if e.name == "probe"]
    assert probe and probe[0].dist.name == "drago-probe"


# ---------------------------------------------------------------------------------------------------
# Reading a run
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_run_reads_config_results_logs_and_world_models(smoke_runs):
    run = api.Run(smoke_runs("continual"))
    assert run.complete and [t["name"] for t in run.tasks] == ["room1", "room2", "room3", "room4"]
    log = run.metrics("eval", as_frame=False)
    assert set(log) >= {"task", "env_step", "episode_reward", "fraction_of_optimal"}
    assert log["env_step"].dtype == np.float64 and log["task"][0] == "room1"
    assert len(run.metrics("train", as_frame=False)["episode_reward"]) > 0
    assert [c.stage for c in run.checkpoints()] == [1, 2, 3, 4]
    model = run.world_model(2)
    predictor = api.load_world_model(run.checkpoint(2))
    obs, action = np.zeros((1, 3), np.float32), np.eye(3, dtype=np.float32)[:1]
    import torch

    with torch.no_grad():
        direct = model(model.encode(torch.from_numpy(obs)), torch.from_numpy(action)).numpy()
    np.testing.assert_array_equal(direct, predictor.predict(obs, action))
    with pytest.raises(api.RunDirError, match="stage 5 is out of range"):
        run.checkpoint(5)
    with pytest.raises(ValueError, match="unknown log 'evals'; choose one of: train, eval, timing"):
        run.metrics("evals")


def test_run_of_a_folder_that_is_not_a_run_says_so(tmp_path):
    with pytest.raises(api.RunDirError, match="is not a drago run directory"):
        api.Run(tmp_path)



def test_preset_plugins_load_by_name_and_bad_ones_are_skipped_with_one_line(tmp_path, monkeypatch, capsys):
    import drago.config as config

    (tmp_path / "quick.yaml").write_text("base: smoke\ntrain:\n  steps_per_task: 300\n")
    fake_distribution(tmp_path, "drago-presets", """
        [drago.presets]
        quick = preset_plugin:QUICK
        smoke = preset_plugin:QUICK
        missing = preset_plugin:MISSING
        """, {"preset_plugin": f"""
        from pathlib import Path
        QUICK = Path({str(tmp_path / 'quick.yaml')!r})
        MISSING = Path({str(tmp_path / 'nope.yaml')!r})
        """})
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(config, "_plugin_presets", None)
    monkeypatch.setattr(config, "_preset_problems", [])
    importlib.invalidate_caches()
    assert api.load_config("quick").train.steps_per_task == 300
    assert "quick" in api.available_presets() and api.load_config("smoke").train.steps_per_task != 300
    warnings = capsys.readouterr().err.strip().splitlines()
    assert len(warnings) == 2
    assert "preset plug-in 'smoke = preset_plugin:QUICK' of package 'drago-presets' skipped: 'smoke' is already a " \
           "preset's name; give the entry point another name" in warnings[0]
    assert "'missing = preset_plugin:MISSING'" in warnings[1] and "does not exist" in warnings[1]
    assert len([p for p in api.plugin_problems() if p.kind == "preset"]) == 2
    sys.modules.pop("preset_plugin", None)
