"""The Python API refuses a bad config in one line naming the key, before anything is written."""

from __future__ import annotations

import pytest

import drago
from drago.config import ConfigError


def smoke():
    return drago.load_config("smoke", ["train.tensorboard=false", "env.tasks=[room1]"])


def test_a_value_of_the_wrong_type_is_refused_before_the_run_directory_exists(tmp_path):
    cfg = smoke()
    cfg.train.steps_per_task = "abc"
    with pytest.raises(ConfigError) as err:
        drago.train(cfg, out=tmp_path / "run", progress=False)
    assert "train.steps_per_task" in str(err.value) and "integer" in str(err.value) and "\n" not in str(err.value)
    assert not (tmp_path / "run").exists()


def test_a_value_out_of_range_is_refused_before_the_run_directory_exists(tmp_path):
    cfg = smoke()
    cfg.agent.tdmpc.discount = 1.5
    with pytest.raises(ConfigError, match="agent.tdmpc.discount"):
        drago.train(cfg, out=tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("section, name, suggestion", [("train", "steps_per_taks", "train.steps_per_task"),
                                                       ("agent", "mlp_dims", "agent.tdmpc.mlp_dim")])
def test_an_unknown_setting_is_refused_where_it_is_set(section, name, suggestion):
    cfg = smoke()
    with pytest.raises(ConfigError) as err:
        setattr(getattr(cfg, section), name, 100)
    assert f"unknown setting '{section}.{name}'" in str(err.value) and f"did you mean {suggestion}?" in str(err.value)


def test_an_unknown_section_is_refused():
    with pytest.raises(ConfigError, match="unknown config section 'trian'"):
        smoke().trian = None


def test_overrides_given_as_one_string_say_how_to_pass_them():
    with pytest.raises(ConfigError, match=r"overrides must be a list of 'key=value' strings, e.g. overrides=\['a=b'\]"):
        drago.load_config("smoke", overrides="a=b")


def test_values_of_the_right_kind_are_normalised(tmp_path):
    cfg = smoke()
    cfg.train.steps_per_task = 200.0  # an integer written as a float
    cfg.env.tasks = ["room1"]  # a list where a tuple is declared
    run = drago.train(cfg, out=tmp_path / "run", progress=False)
    assert run.config.train.steps_per_task == 200 and isinstance(run.config.train.steps_per_task, int)
    assert run.config.env.tasks == ("room1",)


def test_a_methods_own_settings_are_set_checked_and_listed(tmp_path):
    from drago.config import MethodSetting
    from drago.continual import Continual
    from drago.config import METHOD_SETTINGS
    from drago.continual.registry import METHODS, RegistryError

    class Pull(Continual):
        description = "continual TD-MPC that reads a setting of its own"
        settings = {"pull": MethodSetting(float, 0.5, "how hard it pulls")}

        def begin_task(self, task):
            seen.append(self.setting("pull"))

    seen: list[float] = []
    drago.register_method("pull-test", Pull)
    try:
        cfg = drago.load_config("smoke", ["method.pull=2", "train.tensorboard=false", "env.tasks=[room1]",
                                          "train.steps_per_task=200"], method="pull-test")
        assert cfg.method.options == {"pull": 2.0}
        drago.train(cfg, out=tmp_path / "run", progress=False)
        assert seen == [2.0]
        assert ("method.pull", "float, pull-test only", 0.5) in drago.describe_settings(plugins=True)
        with pytest.raises(ConfigError, match=r"did you mean method.pull\? method 'pull-test' declares method.pull"):
            drago.load_config("smoke", ["method.pul=2"], method="pull-test")
        with pytest.raises(ConfigError, match="unknown setting 'method.pull'"):
            drago.load_config("smoke", ["method.pull=2"], method="continual")  # not continual's setting
        cfg.method.options["pull"] = "hard"
        with pytest.raises(ConfigError, match="setting 'method.pull' expects a number"):
            drago.train(cfg, out=tmp_path / "bad", progress=False)
        assert not (tmp_path / "bad").exists()

        class Clash(Continual):
            settings = {"ewc": MethodSetting(float, 1.0, "a built-in section's name")}

        with pytest.raises(RegistryError, match="taken by a built-in setting"):
            drago.register_method("clash-test", Clash)
    finally:
        METHODS.pop("pull-test", None)
        METHOD_SETTINGS.pop("pull-test", None)


def test_every_setting_has_a_description():
    rows = drago.describe_settings_fully()
    assert len(rows) == len(drago.describe_settings())
    assert [key for key, _, _, description in rows if not description.strip()] == []
