"""Held-out transitions and the retention matrix for continuous states (DeepMind Control).

Sources are tiny two-task cheetah runs (four 20-step episodes per task), as in tests/test_dmc.py.
"""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import numpy as np
import pytest
import yaml

if importlib.util.find_spec("dm_control") is None:  # pragma: no cover - depends on the installation
    pytest.skip("dm_control is not installed (pip install -e '.[dmc]')", allow_module_level=True)

from drago import cli, load_world_model  # noqa: E402
from drago.agent.buffer import EpisodeReplay  # noqa: E402
from drago.agent.losses import LOG_EPS  # noqa: E402
from drago.config import load_config  # noqa: E402
from drago.envs import make_env  # noqa: E402
from drago.eval.heldout import (  # noqa: E402
    CSV_COLUMNS,
    HeldoutError,
    heldout_path,
    load_heldout,
    record_heldout,
    retention_matrix,
    write_retention_csv,
)
from drago.report import build_report  # noqa: E402
from drago.training import trainer as trainer_module  # noqa: E402
from drago.seeding import task_seed  # noqa: E402
from helpers import SimulatedCrash, crash_at_call  # noqa: E402

# Every test here reads the DeepMind Control runs the module trains first.
pytestmark = pytest.mark.slow

TASKS = ("cheetah-run", "cheetah-jump")
TINY_CHEETAH = ["env.domain=cheetah", "env.tasks=[cheetah-run,cheetah-jump]", "env.action_repeat=4",
                "env.episode_length=20", "train.steps_per_task=80", "agent.seed_steps=20", "agent.batch_size=16",
                "train.eval_freq=160", "train.checkpoint_freq=80", "train.updates_per_episode=5"]
EPISODES = 2
LENGTH = 20


def train(out: Path, heldout: int = EPISODES) -> int:
    return cli.main(["train", "smoke", "--method", "drago", "--out", str(out), "--no-progress",
                     "train.tensorboard=false", *TINY_CHEETAH, f"train.heldout_episodes={heldout}"])


def checkpoint(run: Path, stage: int) -> Path:
    return run / "checkpoints" / f"task{stage}_{TASKS[stage - 1]}.pt"


def same_logs(a: Path, b: Path) -> None:
    for name in ("train.csv", "eval.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def same_sets(a: Path, b: Path) -> None:
    for stage, task in enumerate(TASKS, start=1):
        for x, y in zip(load_heldout(heldout_path(a, stage, task)), load_heldout(heldout_path(b, stage, task))):
            np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """The same DRAGO run with held-out recording on and off, logging every episode any buffer receives."""
    root = tmp_path_factory.mktemp("heldout")
    out: dict = {"added": {}}
    for name, episodes in (("with", EPISODES), ("without", 0)):
        added: list[tuple[int, int]] = []
        original = EpisodeReplay.add_episode

        def logged(self, obs, *args, _added=added, _original=original, **kwargs):
            _added.append((len(self), len(obs)))
            return _original(self, obs, *args, **kwargs)

        with pytest.MonkeyPatch.context() as m:
            m.setattr(EpisodeReplay, "add_episode", logged)
            assert train(root / name, episodes) == 0
        out[name] = root / name
        out["added"][name] = added
    return out


# ---------------------------------------------------------------------------------------------------
# Recording
# ---------------------------------------------------------------------------------------------------
def test_each_task_ends_with_a_held_out_set_of_final_learner_episodes(runs):
    run = runs["with"]
    for stage, task in enumerate(TASKS, start=1):
        data = load_heldout(run / "heldout" / f"task{stage}_{task}.npz")
        n = EPISODES * LENGTH
        assert data.obs.shape == data.next_obs.shape == (n, 17) and data.action.shape == (n, 6)
        assert data.reward.shape == (n,) and data.obs.dtype == np.float32
        assert np.all(np.abs(data.action) <= 1)
        # Consecutive transitions chain inside an episode, and each episode starts from a fresh reset.
        for e in range(EPISODES):
            rows = slice(e * LENGTH, (e + 1) * LENGTH)
            np.testing.assert_array_equal(data.obs[rows][1:], data.next_obs[rows][:-1])
        env = make_env("cheetah", task, action_repeat=4)
        env.reset(seed=task_seed(1, stage - 1, 4))  # the recording's own env seed, not the training's
        np.testing.assert_array_equal(data.obs[0], env.reset()[0])
        np.testing.assert_array_equal(data.obs[LENGTH], env.reset()[0])
    assert not (runs["without"] / "heldout").exists()
    log = (run / "console.log").read_text()
    assert "held-out set: 2 eval-mode episodes" in log


def test_held_out_data_never_reaches_training(runs):
    # Every buffer received exactly the same episodes (task 1: 4 learner episodes; task 2: 2 learner and
    # 2 reviewer episodes), and the training's logs are byte-identical.
    assert runs["added"]["with"] == runs["added"]["without"] and len(runs["added"]["with"]) == 8
    same_logs(runs["with"], runs["without"])


def test_the_set_is_a_function_of_the_task_checkpoint(runs, tmp_path):
    """What `drago eval heldout` records for an older run is what the trainer recorded live."""
    for stage, task in enumerate(TASKS, start=1):
        again = record_heldout(checkpoint(runs["with"], stage), tmp_path / f"{task}.npz")
        for x, y in zip(load_heldout(again), load_heldout(heldout_path(runs["with"], stage, task))):
            np.testing.assert_array_equal(x, y)


def test_crash_before_the_task_checkpoint_redoes_the_set(runs, tmp_path):
    crashed = tmp_path / "crashed"
    # At the first task checkpoint: task 1's held-out set is recorded, its checkpoint not yet written.
    with crash_at_call(trainer_module, "save_checkpoint", when=lambda path, payload, kind, domain: kind == "task"), \
            pytest.raises(SimulatedCrash):
        train(crashed)
    assert heldout_path(crashed, 1, TASKS[0]).is_file() and not checkpoint(crashed, 1).exists()
    heldout_path(crashed, 1, TASKS[0]).unlink()  # also when the crash came before the set was complete
    assert cli.main(["resume", str(crashed), "--no-progress"]) == 0
    same_logs(crashed, runs["with"])
    same_sets(crashed, runs["with"])


def test_resume_records_the_missing_set_of_a_finished_task(runs, tmp_path):
    crashed = tmp_path / "crashed"
    with crash_at_call(trainer_module.Trainer, "train_task", when=lambda self, index, bar: index == 1), \
            pytest.raises(SimulatedCrash):  # as task 2 starts
        train(crashed)
    heldout_path(crashed, 1, TASKS[0]).unlink()  # a finished task without its set (e.g. an older run)
    assert cli.main(["resume", str(crashed), "--no-progress"]) == 0
    same_logs(crashed, runs["with"])
    same_sets(crashed, runs["with"])


# ---------------------------------------------------------------------------------------------------
# Retention matrix
# ---------------------------------------------------------------------------------------------------
def test_retention_matrix_scores_every_stage_on_every_set(runs):
    rows = retention_matrix(runs["with"])
    assert [tuple(r) for r in rows] == [CSV_COLUMNS] * 4
    assert [(r["stage"], r["stage_task"], r["task_stage"], r["task"]) for r in rows] == [
        (i, TASKS[i - 1], j, TASKS[j - 1]) for i in (1, 2) for j in (1, 2)]
    assert all(r["method"] == "drago" and r["seed"] == 1 and r["n"] == EPISODES * LENGTH for r in rows)
    for r in rows:
        data = load_heldout(heldout_path(runs["with"], r["task_stage"], r["task"]))
        predicted = load_world_model(checkpoint(runs["with"], r["stage"])).predict(data.obs, data.action)
        mse = ((predicted - data.next_obs) ** 2).mean(axis=1)
        assert r["error"] == pytest.approx(float(mse.mean()), rel=1e-5)
        assert r["score"] == pytest.approx(float(np.mean(-np.log(mse + LOG_EPS))), rel=1e-5)
    # The world models of the two stages differ, so their errors on one set do too.
    assert rows[0]["error"] != rows[2]["error"]


def test_eval_heldout_writes_csv(runs, tmp_path, capsys):
    combined = tmp_path / "all.csv"
    assert cli.main(["eval", "heldout", str(runs["with"]), "--out", str(combined)]) == 0
    out = capsys.readouterr().out
    assert "cheetah-jump" in out and f"wrote {runs['with'] / 'retention.csv'}" in out
    rows = retention_matrix(runs["with"])
    for path in (runs["with"] / "retention.csv", combined):
        with path.open(newline="") as handle:
            read = list(csv.DictReader(handle))
        assert [tuple(r) for r in read] == [CSV_COLUMNS] * 4
        assert [float(r["error"]) for r in read] == [r["error"] for r in rows]  # repr: exact round trip
        assert [float(r["score"]) for r in read] == [r["score"] for r in rows]
    write_retention_csv(rows, tmp_path / "again.csv")
    assert (tmp_path / "again.csv").read_bytes() == combined.read_bytes()


def test_eval_heldout_errors_are_one_line(runs, tmp_path, capsys):
    grid = tmp_path / "grid"
    grid.mkdir()
    (grid / "config.yaml").write_text(yaml.safe_dump(load_config("smoke").to_dict(), sort_keys=False))
    for args, expected in (([str(grid)], "use `drago eval coverage` for the grid"),
                           ([str(runs["without"])], "train.heldout_episodes=0"),
                           ([str(runs["with"]), str(tmp_path / "nowhere")], "does not exist")):
        capsys.readouterr()
        assert cli.main(["eval", "heldout", *args]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("drago: error: ") and len(err.splitlines()) == 1 and expected in err, err
    with pytest.raises(HeldoutError, match="minigrid"):
        retention_matrix(grid)


def test_report_shows_the_retention_matrix_of_dmc_runs(runs, tmp_path):
    _, md = build_report([runs["with"], runs["without"]], tmp_path / "report")
    text = md.read_text()
    assert "## World-model retention (held-out transitions)" in text
    assert "| drago | 1: cheetah-run | 1 |" in text and "| drago | 2: cheetah-jump | 1 |" in text
    assert "no held-out set for cheetah-run, cheetah-jump" in text and "train.heldout_episodes=0" in text


def test_dmc_report_has_continual_metrics_from_retention_and_no_grid_sections(runs, tmp_path):
    _, md = build_report([runs["with"]], tmp_path / "report")
    text = md.read_text()
    # R[i][j]: stage i's world model on task j's held-out set, T = 2 stages.
    R = {(r["stage"], r["task_stage"]): r["score"] for r in retention_matrix(runs["with"])}
    acc = (R[(2, 1)] + R[(2, 2)]) / 2
    bwt = R[(2, 1)] - R[(1, 1)]
    assert "## Continual-learning metrics (from held-out retention)" in text
    assert f"| drago | 2 | 1 | {acc:.2f} | {bwt:.2f} | {-bwt:.2f} |" in text
    # Coverage, its metrics and the heatmap are grid-only: absent here, and not reported as missing.
    assert "## World-model coverage" not in text and "(from coverage)" not in text
    assert "grid only" not in text and "heatmap" not in text.lower()
