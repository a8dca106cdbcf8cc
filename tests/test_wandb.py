"""Weights & Biases tracking (train.wandb; docs: Command line and configs, Experiment tracking), in W&B's
offline mode: no network, no account, every W&B folder under the test's tmp_path. What W&B recorded is read
back from its transaction log (``run-ID.wandb``) with W&B's own reader, ``wandb leet inspect --json``.
"""

from __future__ import annotations

import csv
import importlib.abc
import importlib.util
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from drago import cli
from drago.api import load_config, train
from drago.config import Config, ConfigError
from drago.continual.naive import Continual
from drago.training.tracking import default_run_name, last_logged_step
from helpers import crash_at_gradient_step, one_thread_env, sigkill_in_task_two

needs_wandb = pytest.mark.skipif(
    importlib.util.find_spec("wandb") is None,
    reason="wandb is not installed (the wandb extra: pip install -e '.[wandb]'; scripts/setup.sh installs it)")

#: One task of 300 agent steps: the seed phase (200) and one episode with gradient steps, so losses are logged.
TINY = ["env.tasks=[room1]", "train.steps_per_task=300", "agent.tdmpc.lr_schedule_steps=300"]


@pytest.fixture
def offline(monkeypatch, tmp_path) -> Path:
    """W&B offline and silent, its config, cache and data folders in tmp_path; returns that folder."""
    home = tmp_path / "wandb-home"
    for name in ("WANDB_DIR", "WANDB_API_KEY", "WANDB_RUN_ID", "WANDB_RESUME", "WANDB_PROJECT", "WANDB_ENTITY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_ERROR_REPORTING", "false")
    monkeypatch.setenv("WANDB_DISABLE_GIT", "true")
    for name in ("WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR", "WANDB_ARTIFACT_DIR"):
        monkeypatch.setenv(name, str(home / name.lower()))
    return home


def wandb_records(segment: Path) -> list[dict]:
    """Every record of one W&B process's transaction log, read with W&B's reader."""
    (log,) = segment.glob("run-*.wandb")
    done = subprocess.run([sys.executable, "-m", "wandb", "leet", "inspect", "--json", str(log)],
                          capture_output=True, text=True, timeout=300,
                          env={**os.environ, "WANDB_DIR": str(segment.parent)})  # the reader's own log goes there
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines() if line.strip()]


def segments(wandb_dir: Path, run_id: str) -> list[Path]:
    """The offline-run folders of one W&B run, oldest first (one per drago process)."""
    return sorted(wandb_dir.glob(f"wandb/offline-run-*-{run_id}"))


def history(records: list[dict]) -> dict[int, dict[str, float]]:
    """step -> {tag: value} of the W&B history rows, without W&B's own underscore keys."""
    rows = {}
    for record in records:
        if record["type"] == "history":
            item = record["history"]["item"]
            assert item["_step"] not in rows, f"step {item['_step']} written twice"
            rows[item["_step"]] = {k: v for k, v in item.items() if not k.startswith("_")}
    return rows


def csv_scalars(run: Path, global_step) -> dict[int, dict[str, float]]:
    """What TensorBoard and W&B should hold, from the CSV logs: step -> {tag: value}."""
    expected: dict[int, dict[str, float]] = {}
    for kind in ("train", "eval"):
        with (run / f"{kind}.csv").open(newline="") as handle:
            for row in csv.DictReader(handle):
                prefix = kind if kind == "train" else f"{kind}/{row['task']}"
                step = global_step(int(row["task_index"]), int(row["step"]))
                expected.setdefault(step, {}).update(
                    {f"{prefix}/{k}": float(v) for k, v in row.items() if k not in ("task", "task_index") and v != ""})
    return expected


# ---------------------------------------------------------------------------------------------------
# What W&B receives
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
@needs_wandb
def test_wandb_gets_tensorboards_scalars_and_the_whole_config(offline, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = tmp_path / "run"
    assert cli.main(["train", "smoke", "--out", str(run), "--no-progress", *TINY, "train.wandb=offline",
                     "train.wandb_tags=[smoke,ci]", "train.wandb_group=tests"]) == 0
    run_id = json.loads((run / "wandb.json").read_text())["id"]
    (segment,) = segments(run, run_id)  # W&B's files sit in the run directory when WANDB_DIR is unset
    records = wandb_records(segment)

    (start,) = [r["run"] for r in records if r["type"] == "run"]
    assert start["run_id"] == run_id and start["project"] == "drago" and start["display_name"] == "smoke/continual/seed1"
    assert start["tags"] == ["smoke", "ci"] and start["run_group"] == "tests" and start["job_type"] == "train"
    config = {k: v for k, v in start["config"]["update"].items() if k != "_wandb"}
    cfg = Config.from_dict(yaml.safe_load((run / "config.yaml").read_text()))
    assert config == json.loads(json.dumps(cfg.to_dict()))

    logged = history(records)
    assert logged == csv_scalars(run, lambda index, step: step)  # every scalar, its tag and step, nothing else
    assert any(tag.startswith("train/learner_") for values in logged.values() for tag in values)

    events = EventAccumulator(str(run / "tb"))
    events.Reload()
    tensorboard = {(tag, event.step): event.value for tag in events.Tags()["scalars"] for event in events.Scalars(tag)}
    assert tensorboard.keys() == {(tag, step) for step, values in logged.items() for tag in values}
    for (tag, step), value in tensorboard.items():
        assert value == pytest.approx(logged[step][tag], rel=1e-6, abs=1e-6), (tag, step)  # TensorBoard keeps float32
    assert any(r["type"] == "exit" and r["exit"].get("exit_code", 0) == 0 for r in records)

    # What a resume reads from an earlier offline process: the last step, also from a log cut short by a kill.
    (log,) = segment.glob("run-*.wandb")
    assert last_logged_step(log) == 300
    cut = tmp_path / "cut" / log.name
    cut.parent.mkdir()
    cut.write_bytes(log.read_bytes()[:7])  # W&B's header alone: nothing logged
    assert last_logged_step(cut) is None


@pytest.mark.slow
@needs_wandb
def test_a_resumed_run_continues_the_same_wandb_run_without_repeating_a_step(offline, tmp_path, monkeypatch):
    """A crash after a periodic checkpoint; `drago resume` continues the W&B run under the same id and sends only
    the steps W&B does not hold yet, so the two offline folders hold every step once."""
    wandb_dir = offline / "dir"
    wandb_dir.mkdir(parents=True)  # W&B falls back to the working directory when WANDB_DIR does not exist
    monkeypatch.setenv("WANDB_DIR", str(wandb_dir))  # W&B's files away from the run: the resume still finds them
    run = tmp_path / "run"
    overrides = ["env.tasks=[room1]", "train.wandb=offline", "train.tensorboard=false"]
    # in episode 4: episode 3 (step 300) is logged past the checkpoint at 200
    with crash_at_gradient_step(Continual, 16), pytest.raises(RuntimeError, match="simulated crash"):
        cli.main(["train", "smoke", "--out", str(run), "--no-progress", *overrides])
    run_id = json.loads((run / "wandb.json").read_text())["id"]
    assert cli.main(["resume", str(run), "--no-progress"]) == 0
    assert json.loads((run / "wandb.json").read_text())["id"] == run_id
    assert f"W&B: continuing run {run_id}, which holds the steps up to 300" in (run / "console.log").read_text()

    first, second = [wandb_records(segment) for segment in segments(wandb_dir, run_id)]
    starts = [r["run"] for records in (first, second) for r in records if r["type"] == "run"]
    assert [s["run_id"] for s in starts] == [run_id, run_id] and starts[1].get("resume") is True
    before, after = history(first), history(second)
    assert max(before) == 300 and min(after) == 400  # the replayed step 300 was not sent again
    # Together the two processes logged what one uninterrupted run logs (the CSV files equal it; see test_trainer).
    assert {**before, **after} == csv_scalars(run, lambda index, step: step)
    # The crashed process's W&B run ended as failed, the resumed one as finished.
    exits = [[r["exit"].get("exit_code", 0) for r in records if r["type"] == "exit"] for records in (first, second)]
    assert exits == [[1], [0]]


@needs_wandb
@pytest.mark.experiment
def test_sigkill_then_resume_continues_the_wandb_run(offline, tmp_path):
    """A real kill: W&B loses what it had not yet written (it writes its log in blocks), and the resumed process
    sends every step after the last one the killed process's log holds, so no step is missing or repeated.

    The parent holds a W&B service of its own, as a notebook or script that used W&B does: its children inherit
    the service's address, and a killed child's run would stay open in that service and refuse the resume."""
    import wandb

    wandb.teardown()  # a service this process already has may have left the environment (drago.cli.main)
    wandb.setup()
    assert "WANDB_SERVICE" in os.environ
    try:
        _kill_and_resume(tmp_path)
    finally:
        wandb.teardown()


def _kill_and_resume(tmp_path: Path) -> None:
    run = tmp_path / "killed"
    longer = ["env.tasks=[room1,room2]", "train.steps_per_task=600", "train.checkpoint_freq=100",
              "train.wandb=offline", "train.tensorboard=false"]
    drago = Path(sys.executable).parent / "drago"
    # Killed in task 2, after task 1's rows went to W&B.
    assert sigkill_in_task_two(["smoke", "--no-progress", *longer], run, tmp_path, wait_s=120) == -signal.SIGKILL
    done = subprocess.run([str(drago), "resume", str(run), "--no-progress"], capture_output=True, text=True,
                          env=one_thread_env(), cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr
    run_id = json.loads((run / "wandb.json").read_text())["id"]
    first, second = [history(wandb_records(segment)) for segment in segments(run, run_id)]
    assert not first or max(first) < min(second)
    expected = csv_scalars(run, lambda index, step: index * 600 + step)
    # What the killed process logged up to its checkpoint but W&B had not written yet is lost to W&B (task 1's
    # last rows, when the kill came soon after them); everything W&B holds is what the CSV logs hold, and after
    # the resumed process's first step it holds every step.
    logged = {**first, **second}
    assert all(values.items() <= expected[step].items() for step, values in logged.items())
    assert all(second.get(step) == expected[step] for step in expected if step > min(second))


# ---------------------------------------------------------------------------------------------------
# Off by default, and a clear line without wandb
# ---------------------------------------------------------------------------------------------------
class _RecordWandbImports(importlib.abc.MetaPathFinder):
    def __init__(self):
        self.attempts: list[str] = []

    def find_spec(self, name, path=None, target=None):
        if name == "wandb" or name.startswith("wandb."):
            self.attempts.append(name)
            raise ImportError(f"test: {name} must not be imported")
        return None


def test_with_the_setting_off_nothing_imports_wandb(tmp_path, monkeypatch):
    recorder = _RecordWandbImports()
    for name in [m for m in sys.modules if m == "wandb" or m.startswith("wandb.")]:
        monkeypatch.delitem(sys.modules, name)  # restored afterwards; an import now has to ask the finders
    monkeypatch.setattr(sys, "meta_path", [recorder, *sys.meta_path])
    assert load_config("smoke").train.wandb == "off"
    train(load_config("smoke", ["env.tasks=[room1]", "train.steps_per_task=200"]), out=tmp_path / "run",
          progress=False)
    assert recorder.attempts == []
    assert not (tmp_path / "run" / "wandb.json").exists() and not (tmp_path / "run" / "wandb").exists()


def test_without_wandb_the_setting_fails_in_one_line_before_the_run_starts(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "wandb", None)  # what importlib sees when wandb is not installed
    run = tmp_path / "run"
    assert cli.main(["train", "smoke", "--out", str(run), "--no-progress", "train.wandb=online"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("drago: error: train.wandb=online needs Weights & Biases, which is not installed: "
                   "pip install 'drago[wandb]'")
    assert not run.exists()


# ---------------------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------------------
def test_the_setting_takes_a_mode_or_a_boolean():
    for value, mode in (("off", "off"), ("online", "online"), ("offline", "offline"), ("false", "off"),
                        ("no", "off"), ("true", "online")):
        assert load_config("smoke", [f"train.wandb={value}"]).train.wandb == mode, value
    with pytest.raises(ConfigError, match=r"unknown train.wandb 'cloud'; valid choices: off, online, offline"):
        load_config("smoke", ["train.wandb=cloud"])
    cfg = load_config("smoke", ["train.wandb=offline", "wandb_tags=[a,b]"])
    assert Config.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_default_run_names():
    cfg = load_config("smoke", method="drago", seed=3)
    assert default_run_name(cfg) == "smoke/drago/seed3"
    cfg.transfer.checkpoint, cfg.transfer.after, cfg.env.tasks = "../checkpoints/task2_room2.pt", 2, ("room3",)
    assert default_run_name(cfg) == "smoke/drago/seed3/transfer/room3-after2"
