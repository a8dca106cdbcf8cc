"""Settings in sections per agent kind and per method (docs: Settings): what a run reads, what it refuses, and
the runs, checkpoints and records written with the old flat names, read as before."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import drago
from drago.config import RENAMED, ConfigError, inapplicable_settings, load_config
from drago.eval import unit
from drago.study.plan import DONE, START, StudyError, plan_study, record_verdict
from drago.training.records import materialize, protocol_digest, read_record, run_protocol
from drago.training.rundir import config_diffs, read_run_config

ROOT = Path(__file__).resolve().parents[1]
#: A unit of the grid study recorded before the sections existed (record format version 1, flat names), as
#: committed in results/grid/drago-no-reviewer/seed1.json.gz at 7f49cd3.
FLAT_RECORD = ROOT / "tests" / "data" / "record-v1-drago-no-reviewer-seed1.json.gz"


@pytest.mark.parametrize("override, message", [
    ("agent.horizon=5", "setting 'agent.horizon' was renamed; write agent.tdmpc.horizon=5"),
    ("pets_horizon=5", "setting 'pets_horizon' was renamed; write agent.pets.horizon=5"),
    ("method.ewc_coef=3", "setting 'method.ewc_coef' was renamed; write method.ewc.coef=3"),
    ("method.rehearsal_lambda=2", "setting 'method.rehearsal_lambda' was renamed; write method.rehearsal.weight=2"),
    ("agent.momentum=0.2", "setting 'agent.momentum' was renamed; write agent.tdmpc.momentum=0.2 and "
                           "agent.pets.momentum=0.2"),
    ("horizon=5", "setting 'horizon' is ambiguous; write one of: agent.tdmpc.horizon, agent.pets.horizon"),
    ("agent.tdmpc=5", "'agent.tdmpc' is a section, not a setting"),
])
def test_an_old_or_unclear_key_gets_one_line_with_the_key_to_write(override, message):
    with pytest.raises(ConfigError, match="^" + message.replace("(", r"\(").replace(".", r"\.")):
        load_config("smoke", [override])


def test_every_old_key_names_a_setting_that_exists():
    keys = {key for key, _, _ in drago.describe_settings()}
    assert len(RENAMED) >= 50 and all(set(new) <= keys for new in RENAMED.values())


@pytest.mark.parametrize("overrides, method, readers", [
    (["agent.pets.horizon=5"], "drago", "agent.kind=pets"),
    (["agent.tdmpc.lr_final=1e-4", "agent.kind=pets"], "continual", "agent.kind=tdmpc"),
    (["method.ewc.coef=5"], "drago", "method ewc"),
    (["method.rehearsal.batch=64"], "drago-no-rehearsal", "methods drago, drago-no-reviewer, drago-single-agent, "
                                                           "pseudo-rehearsal"),
    (["method.reviewer.cost_coef=1"], "continual", "methods drago, drago-no-rehearsal"),
])
def test_a_setting_the_run_would_ignore_is_refused_naming_who_reads_it(overrides, method, readers):
    with pytest.raises(ConfigError) as err:
        drago.load_config("smoke", overrides, method=method)
    assert str(err.value).startswith(f"setting '{overrides[0].partition('=')[0]}' applies to {readers}")
    assert "\n" not in str(err.value) and str(err.value).endswith("remove it")


def test_the_rehearsal_weight_is_read_only_in_joint_mode():
    # Separate mode (the default) takes its own optimizer step and has no weight to set.
    with pytest.raises(ConfigError, match="^setting 'method.rehearsal.weight' .* add method.rehearsal.mode=joint"):
        drago.load_config("smoke", ["method.rehearsal.weight=0"], method="drago-no-reviewer")
    cfg = drago.load_config("smoke", ["method.rehearsal.mode=joint", "method.rehearsal.weight=0.5"],
                            method="drago-no-reviewer")
    assert (cfg.method.rehearsal.mode, cfg.method.rehearsal.weight) == ("joint", 0.5)


def test_the_same_settings_apply_where_they_are_read_and_presets_may_set_any_section():
    cfg = drago.load_config("smoke", ["method.ewc.coef=5", "agent.tdmpc.horizon=4"], method="ewc")
    assert (cfg.method.ewc.coef, cfg.agent.tdmpc.horizon) == (5.0, 4)
    pets = drago.load_config("minigrid-pets-cpu", ["agent.pets.horizon=7"], method="drago")
    assert pets.agent.pets.horizon == 7
    # The smoke preset sizes both kinds: its agent.pets section is read by PETS runs and ignored by TD-MPC ones.
    assert drago.load_config("smoke").agent.pets.members == 2
    assert {"agent.pets.members", "method.ewc.coef"} <= set(inapplicable_settings(drago.load_config("smoke")))


def test_a_protocol_holds_only_what_its_run_reads(tmp_path):
    preset = tmp_path / "mine.yaml"
    digests = {}
    for coef in (1.0, 9.0):
        preset.write_text(f"base: smoke\nmethod:\n  ewc:\n    coef: {coef}\n")
        digests[coef] = {method: protocol_digest(run_protocol(load_config(str(preset), method=method), {}, []))
                         for method in ("drago", "ewc")}
    assert digests[1.0]["drago"] == digests[9.0]["drago"]  # drago never reads method.ewc
    assert digests[1.0]["ewc"] != digests[9.0]["ewc"]


def test_a_study_passes_each_run_the_overrides_its_method_reads(tmp_path):
    plan = plan_study("smoke", methods=["drago", "ewc"], seeds=[1], out=tmp_path / "study", transfers=False,
                      overrides=["method.ewc.coef=5", "method.rehearsal.batch=64", "train.seed=1"])
    argv = {run.method: run.argv for run in plan.runs}
    assert "method.ewc.coef=5" in argv["ewc"] and "method.ewc.coef=5" not in argv["drago"]
    assert "method.rehearsal.batch=64" in argv["drago"] and "method.rehearsal.batch=64" not in argv["ewc"]
    with pytest.raises(StudyError, match="^setting 'method.replay.capacity' applies to method replay, and none of "
                                         "this study's runs reads it"):
        plan_study("smoke", methods=["drago", "ewc"], seeds=[1], out=tmp_path / "other", transfers=False,
                   overrides=["method.replay.capacity=10"])


def test_a_run_written_with_the_flat_names_is_read_with_the_same_settings(tmp_path):
    view = materialize(read_record(FLAT_RECORD), tmp_path / "view")
    assert "vae_hidden_dim" in (view / "config.yaml").read_text()  # written before the sections existed
    cfg = read_run_config(view)
    wanted = load_config("minigrid-cpu", ["train.threads=1"], method="drago-no-reviewer", seed=1)
    assert (cfg.agent.tdmpc.horizon, cfg.method.vae.hidden_dim, cfg.method.rehearsal.freq) == (5, 64, 1)
    assert [d for d in config_diffs(cfg, wanted) if not d.startswith("agent.schedule_clock")] == []


def test_a_record_written_with_the_flat_names_keeps_its_settings(tmp_path, monkeypatch):
    """A record of version 1 is read as this version, with the settings today's code computes for its unit: with
    the evaluations of its day, a study with it in its records folder does not run that unit again."""
    record = read_record(FLAT_RECORD)
    assert record["version"] == 2 and "agent.tdmpc.horizon" in record["protocol"]["run"]
    assert not any(key.startswith(("agent.pets.", "method.ewc.")) for key in record["protocol"]["run"])
    records = tmp_path / "records"
    (records / "drago-no-reviewer").mkdir(parents=True)
    shutil.copy(FLAT_RECORD, records / "drago-no-reviewer" / "seed1.json.gz")
    monkeypatch.setattr(unit, "EVALUATION_VERSIONS", {})  # the evaluations as they were when it was recorded
    plan = plan_study("minigrid-cpu", methods=["drago-no-reviewer"], seeds=[1, 2], out=tmp_path / "study",
                      overrides=["train.threads=1"], records=records)
    # Seed 1 is recorded with the study's protocol: done, nothing to run or record again.
    assert [(run.seed, run.state, run.recorded) for run in plan.runs] == [(1, DONE, True), (2, START, False)]
    assert [job.seed for job in plan.record_jobs] == [2]


def test_a_unit_recorded_with_an_earlier_evaluation_is_recorded_again(tmp_path):
    """Today's swap test (components@N, N > 1) is not the one in the version-1 record: its unit is due again, and the
    plan says why."""
    records = tmp_path / "records"
    (records / "drago-no-reviewer").mkdir(parents=True)
    shutil.copy(FLAT_RECORD, records / "drago-no-reviewer" / "seed1.json.gz")
    plan = plan_study("minigrid-cpu", methods=["drago-no-reviewer"], seeds=[1], out=tmp_path / "study",
                      overrides=["train.threads=1"], records=records)
    assert [(run.seed, run.state, run.recorded) for run in plan.runs] == [(1, START, False)]
    assert [job.seed for job in plan.record_jobs] == [1]
    assert record_verdict(records / "drago-no-reviewer" / "seed1.json.gz", plan.record_jobs[0].protocol).count(
        "components") >= 1


def test_every_setting_the_docs_and_presets_name_exists():
    """A `section.key=value` in the README, the docs, the presets or the example package names a setting of
    today (the changelog keeps history; the extending page's example is a plug-in method's own setting)."""
    import re

    keys = {key for key, _, _ in drago.describe_settings()} | {"method.anchor_coef"}
    named = re.compile(r"(?<![\w.])((?:env|agent|train|method|transfer)\.[a-z_][a-z0-9_.]*[a-z0-9_])=")
    files = [ROOT / "README.md", *(ROOT / "docs").rglob("*.md"), *(ROOT / "drago" / "presets").glob("*.yaml"),
             *(ROOT / "examples").rglob("*.md")]
    stale = [f"{path.relative_to(ROOT)}: {match.group(1)}" for path in files if path.name != "changelog.md"
             for match in named.finditer(path.read_text(encoding="utf-8")) if match.group(1) not in keys]
    assert stale == []
