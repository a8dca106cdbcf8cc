"""World-model coverage (grid) and the public `load_world_model` API.

One smoke run (four tasks of 400 agent steps, a few seconds) is shared by the module.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import drago
from drago import cli
from drago.agent.losses import LOG_EPS
from drago.api import WorldModelPredictor, load_world_model
from drago.envs.fourrooms import (
    OPENINGS,
    decode_observation,
    next_state,
    observation,
    traversable_cells,
)
from drago.eval.coverage import (
    CSV_COLUMNS,
    GROUPS,
    decode_batch,
    grid_coverage,
    grid_transitions,
    room_of,
)
from drago.training.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from helpers import read_csv

TASKS = ("room1", "room2", "room3", "room4")
N_TRANSITIONS = 561 * 4 * 3


@pytest.fixture(scope="module")
def smoke_run(smoke_runs) -> Path:
    return smoke_runs("continual")


def task_checkpoint(run: Path, index: int) -> Path:
    return run / "checkpoints" / f"task{index + 1}_{TASKS[index]}.pt"


class Oracle:
    """Predicts the true next observation of every transition of `grid_transitions()`."""

    def predict(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        out = []
        for o, a in zip(obs, action):
            x, y, d = decode_observation(o)
            (nx, ny), nd = next_state((x, y), d, int(np.argmax(a)))
            out.append(observation((nx, ny), nd))
        return np.asarray(out)


class Still:
    """Predicts that nothing changes."""

    def predict(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        return np.array(obs, copy=True)


# ---------------------------------------------------------------------------------------------------
# transitions and rooms
# ---------------------------------------------------------------------------------------------------
def test_grid_transitions_enumerate_every_state_action():
    obs, actions, next_obs, cells, headings, action_idx = grid_transitions()
    assert len(obs) == N_TRANSITIONS
    for array, width in ((obs, 3), (actions, 3), (next_obs, 3), (cells, 2)):
        assert array.shape == (N_TRANSITIONS, width)
    assert headings.shape == action_idx.shape == (N_TRANSITIONS,)
    keys = {(x, y, d, a) for (x, y), d, a in zip(cells.tolist(), headings.tolist(), action_idx.tolist())}
    assert keys == {(x, y, d, a) for x, y in traversable_cells() for d in range(4) for a in range(3)}
    np.testing.assert_array_equal(actions, np.eye(3, dtype=np.float32)[action_idx])
    assert grid_transitions() is grid_transitions()  # cached
    assert not obs.flags.writeable  # shared through the cache


def test_true_next_states_match_the_transition_function():
    data = grid_transitions()
    for i in range(N_TRANSITIONS):
        cell = tuple(data.cells[i])
        np.testing.assert_array_equal(data.obs[i], observation(cell, data.headings[i]))
        expected = observation(*next_state(cell, int(data.headings[i]), int(data.action_idx[i])))
        np.testing.assert_array_equal(data.next_obs[i], expected)


def test_forward_into_a_wall_keeps_the_cell():
    data = grid_transitions()
    # (1, 1) facing north (3) looks at the outer wall; facing west (2) too.
    for heading in (2, 3):
        row = np.flatnonzero((data.cells == (1, 1)).all(1) & (data.headings == heading) & (data.action_idx == 2))
        assert len(row) == 1
        np.testing.assert_array_equal(data.next_obs[row[0]], data.obs[row[0]])
    # Facing east it moves.
    row = np.flatnonzero((data.cells == (1, 1)).all(1) & (data.headings == 0) & (data.action_idx == 2))[0]
    assert decode_observation(data.next_obs[row]) == (2, 1, 0)


def test_room_of():
    assert room_of((1, 1)) == 1 and room_of((25, 1)) == 2 and room_of((1, 25)) == 3 and room_of((25, 25)) == 4
    assert room_of((12, 12)) == 1 and room_of((14, 12)) == 2 and room_of((12, 14)) == 3 and room_of((14, 14)) == 4
    for cell in OPENINGS:
        assert room_of(cell) is None
    assert [c for c in traversable_cells() if room_of(c) is None] == sorted(OPENINGS, key=lambda c: (c[1], c[0]))


def test_decode_batch_agrees_with_decode_observation():
    rng = np.random.default_rng(0)
    # Mostly in range, some beyond it (clipping), and values exactly halfway between cells (rounding).
    preds = np.concatenate([rng.uniform(-1.3, 1.3, (2000, 3)),
                            grid_transitions().obs + np.float32(1.0 / 27.0)]).astype(np.float32)
    decoded = decode_batch(preds)
    assert [tuple(r) for r in decoded.tolist()] == [decode_observation(p) for p in preds]
    assert (decode_batch(np.array([[np.nan, 0, 0]], dtype=np.float32)) == -1).all()


# ---------------------------------------------------------------------------------------------------
# coverage of hand-made predictors
# ---------------------------------------------------------------------------------------------------
def test_oracle_is_perfect_everywhere():
    result = grid_coverage(Oracle())
    assert list(result.rooms) == list(GROUPS)
    for group, summary in result.rooms.items():
        assert summary["accuracy"] == 1.0, group
        assert summary["score"] == pytest.approx(-np.log(LOG_EPS)), group
    assert result.correct.all()
    assert result.rooms["all"]["n"] == N_TRANSITIONS
    assert sum(result.rooms[g]["n"] for g in GROUPS if g != "all") == N_TRANSITIONS
    assert result.rooms["corridor"]["n"] == len(OPENINGS) * 12


def test_identity_predictor_is_right_only_where_nothing_moves():
    # Independently of the env: turning always changes the heading, so only forward into a blocked
    # cell (wall or block) leaves the state unchanged.
    stays = {}
    for cell in traversable_cells():
        room = room_of(cell)
        group = "corridor" if room is None else f"room{room}"
        for d in range(4):
            for a in range(3):
                stays.setdefault(group, []).append(next_state(cell, d, a) == (cell, d))
    assert all(next_state(cell, d, a)[1] != d for cell in traversable_cells() for d in range(4) for a in (0, 1))

    result = grid_coverage(Still())
    for group, flags in stays.items():
        assert result.rooms[group]["accuracy"] == pytest.approx(np.mean(flags), abs=1e-15), group
        assert result.rooms[group]["n"] == len(flags)
    everything = [f for flags in stays.values() for f in flags]
    assert result.rooms["all"]["accuracy"] == pytest.approx(np.mean(everything), abs=1e-15)
    assert 0.0 < result.rooms["all"]["accuracy"] < 1.0 / 3.0
    # Unchanged rows score -log(eps); moved rows are off by at least one cell step.
    data = grid_transitions()
    moved = ~result.correct
    np.testing.assert_allclose(result.score[result.correct], -np.log(LOG_EPS))
    expected = -np.log(((data.obs[moved].astype(np.float64) - data.next_obs[moved]) ** 2).mean(1) + LOG_EPS)
    np.testing.assert_allclose(result.score[moved], expected)


def test_bad_predictor_shape_is_rejected():
    class Wrong:
        def predict(self, obs, action):
            return obs[:, :2]

    with pytest.raises(ValueError, match="shape"):
        grid_coverage(Wrong())


# ---------------------------------------------------------------------------------------------------
# load_world_model on a real run
# ---------------------------------------------------------------------------------------------------
def test_public_api_is_exported_lazily():
    assert drago.load_world_model is load_world_model
    code = "import sys, drago; assert 'torch' not in sys.modules and 'tensorboard' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.slow
def test_load_world_model_predicts_as_the_network(smoke_run):
    path = task_checkpoint(smoke_run, 2)
    predictor = load_world_model(path)
    assert isinstance(predictor, WorldModelPredictor)
    assert (predictor.obs_dim, predictor.action_dim) == (3, 3)
    assert (predictor.domain, predictor.task, predictor.task_index) == ("minigrid", "room3", 2)

    stored = load_checkpoint(path, kind="task")["world_model"]
    for key, value in predictor.world_model.state_dict().items():
        torch.testing.assert_close(value, stored[key], rtol=0, atol=0)

    data = grid_transitions()
    predicted = predictor.predict(data.obs, data.actions)
    assert predicted.shape == (N_TRANSITIONS, 3) and predicted.dtype == np.float32
    with torch.no_grad():
        direct = predictor.world_model(torch.from_numpy(data.obs.copy()), torch.from_numpy(data.actions.copy()))
    np.testing.assert_array_equal(predicted, direct.numpy())
    assert np.abs(predicted).max() <= 1.0  # the grid's dynamics end in tanh
    # Chunking does not change the answer (up to float rounding: matmul kernels depend on batch size).
    from drago.eval import predictor as predictor_module
    old, predictor_module.PREDICT_CHUNK = predictor_module.PREDICT_CHUNK, 1000
    try:
        np.testing.assert_allclose(predictor.predict(data.obs, data.actions), predicted, rtol=0, atol=1e-6)
    finally:
        predictor_module.PREDICT_CHUNK = old
    # Lists and float64 are accepted.
    np.testing.assert_allclose(predictor.predict(data.obs[:2].astype(np.float64).tolist(), data.actions[:2]),
                               predicted[:2], rtol=0, atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("obs_shape, action_shape", [((5, 2), (5, 3)), ((5, 3), (5, 4)), ((5, 3), (4, 3)),
                                                     ((3,), (3,)), ((5, 3, 1), (5, 3))])
def test_predict_rejects_wrong_shapes(smoke_run, obs_shape, action_shape):
    predictor = load_world_model(task_checkpoint(smoke_run, 0))
    with pytest.raises(ValueError, match=r"expects obs of shape \(N, 3\) and action of shape \(N, 3\)") as info:
        predictor.predict(np.zeros(obs_shape), np.zeros(action_shape))
    assert "\n" not in str(info.value)


@pytest.mark.slow
def test_load_world_model_refuses_bad_checkpoints(smoke_run, tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        load_world_model(tmp_path / "missing.pt")
    save_checkpoint(tmp_path / "resume.pt", {"task_index": 0}, kind="resume", domain="minigrid")
    with pytest.raises(CheckpointError, match="'resume' checkpoint"):
        load_world_model(tmp_path / "resume.pt")
    # Weights of another width than the stored config describes.
    data = load_checkpoint(task_checkpoint(smoke_run, 0), kind="task")
    data["config"]["agent"]["tdmpc"]["mlp_dim"] = 16
    payload = {k: v for k, v in data.items() if k not in ("format", "version", "kind", "domain")}
    save_checkpoint(tmp_path / "task1_room1.pt", payload, kind="task", domain="minigrid")
    with pytest.raises(CheckpointError, match="does not match its config") as info:
        load_world_model(tmp_path / "task1_room1.pt")
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------------
# drago eval coverage
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_eval_coverage_writes_csv(smoke_run, tmp_path, capsys):
    combined = tmp_path / "all.csv"
    assert cli.main(["eval", "coverage", str(smoke_run), "--out", str(combined)]) == 0
    out = capsys.readouterr().out
    with capsys.disabled():
        print("\n" + out)
    rows = read_csv(smoke_run / "coverage.csv")
    assert rows == read_csv(combined)
    assert list(rows[0]) == list(CSV_COLUMNS)
    assert len(rows) == len(TASKS) * len(GROUPS)
    assert [(int(r["stage"]), r["stage_task"], r["room"]) for r in rows] == [
        (i + 1, task, group) for i, task in enumerate(TASKS) for group in GROUPS]
    for row in rows:
        assert 0.0 <= float(row["accuracy"]) <= 1.0
        assert np.isfinite(float(row["score"]))
        assert (row["run"], row["method"], row["seed"]) == (str(smoke_run), "continual", "1")
    assert {int(r["n"]) for r in rows if r["room"].startswith("room")} == {139 * 12}
    # The CSV matches an evaluation by the library of the stage-2 model.
    result = grid_coverage(load_world_model(task_checkpoint(smoke_run, 1)))
    for row in rows:
        if row["stage"] == "2":
            assert float(row["accuracy"]) == result.rooms[row["room"]]["accuracy"]
            assert float(row["score"]) == result.rooms[row["room"]]["score"]
    table = out.splitlines()
    assert any(line.split()[:3] == [str(smoke_run), "4", "room4"] for line in table)


@pytest.mark.slow
def test_eval_coverage_of_a_run_in_progress_covers_finished_tasks(smoke_run, tmp_path):
    partial = tmp_path / "partial"
    (partial / "checkpoints").mkdir(parents=True)
    (partial / "config.yaml").write_text((smoke_run / "config.yaml").read_text())
    for index in (0, 1):
        (partial / "checkpoints" / task_checkpoint(smoke_run, index).name).write_bytes(
            task_checkpoint(smoke_run, index).read_bytes())
    assert cli.main(["eval", "coverage", str(partial)]) == 0
    assert {r["stage"] for r in read_csv(partial / "coverage.csv")} == {"1", "2"}


def one_line_error(capsys, argv: list[str], fragment: str) -> None:
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("drago: error: ") and fragment in lines[0], lines[0]


@pytest.mark.slow
def test_eval_coverage_errors_are_one_line(smoke_run, tmp_path, capsys):
    not_a_run = tmp_path / "notes"
    not_a_run.mkdir()
    one_line_error(capsys, ["eval", "coverage", str(not_a_run)], "not a drago run directory")
    one_line_error(capsys, ["eval", "coverage", str(tmp_path / "missing")], "does not exist")

    empty = tmp_path / "fresh"
    empty.mkdir()
    (empty / "config.yaml").write_text((smoke_run / "config.yaml").read_text())
    one_line_error(capsys, ["eval", "coverage", str(empty)], "no task checkpoint")
    # A good run first does not hide a bad one later, and nothing is written for either.
    (smoke_run / "coverage.csv").unlink(missing_ok=True)
    one_line_error(capsys, ["eval", "coverage", str(smoke_run), str(empty)], "no task checkpoint")
    assert not (smoke_run / "coverage.csv").exists()

    corrupt = tmp_path / "corrupt"
    (corrupt / "checkpoints").mkdir(parents=True)
    (corrupt / "config.yaml").write_text((smoke_run / "config.yaml").read_text())
    (corrupt / "checkpoints" / "task1_room1.pt").write_bytes(b"garbage")
    one_line_error(capsys, ["eval", "coverage", str(corrupt)], "task1_room1.pt")

    other = tmp_path / "other-domain"
    other.mkdir()
    (other / "config.yaml").write_text((smoke_run / "config.yaml").read_text().replace("domain: minigrid",
                                                                                      "domain: cheetah"))
    one_line_error(capsys, ["eval", "coverage", str(other)], "cheetah")

    one_line_error(capsys, ["eval"], "required")
    one_line_error(capsys, ["eval", "coverage"], "required")
    one_line_error(capsys, ["eval", "coverage", str(smoke_run), "--bogus"], "--bogus")
