"""Zero-shot planning with the world model and the true reward (drago.eval.zero_shot).

The smoke preset's continual run (four tasks, trained once per session) gives a world model per stage;
its models learned almost nothing, which is fine: the matrix's shape, seeding and files are what is tested
here, and the ceiling (true dynamics) tests the planner.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import read_csv

from drago.config import load_config
from drago.envs import GRID_TASKS, make_env, task_optimum
from drago.envs.fourrooms import EPISODE_LENGTH, next_state, observation
from drago.envs.tasks import get_grid_task
from drago.eval.coverage import decode_batch, grid_transitions
from drago.eval.predictor import load_world_model
from drago.eval.zero_shot import (
    CSV_COLUMNS,
    DEFAULT_EPSILON,
    LOST,
    LatticePlanner,
    ZeroShotError,
    ceiling,
    decode_obs,
    default_tasks,
    format_table,
    is_paper_case,
    lattice_model,
    matrix_metrics,
    model_dynamics,
    play,
    return_matrix,
    state_index,
    true_dynamics,
    true_reward,
    write_zero_shot_csv,
    zero_shot_matrix,
)
from drago.training.rundir import write_run_config

TRAINING = ("room1", "room2", "room3", "room4")
TRANSFERS = ("room1to2", "room1to3", "room3to4")
#: The small budget of the planner tests: a 25-step lookahead sees every goal of the catalogue from its start
#: (the farthest, room2's, is 22 steps away; benchmarks/zero_shot_ceiling.py); the tolerance is 1% of the
#: DP optimum.
SMALL_HORIZON = 25
TOLERANCE = 0.01


@pytest.fixture(scope="module")
def smoke_run(smoke_runs) -> Path:
    return smoke_runs("continual")


# ---------------------------------------------------------------------------------------------------
# the true reward and the true dynamics
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dense", [True, False])
def test_true_reward_is_the_envs_on_every_grid_transition(dense):
    data = grid_transitions()
    obs, actions, next_obs = (torch.from_numpy(np.array(a)) for a in (data.obs, data.actions, data.next_obs))
    for name in GRID_TASKS:
        task = get_grid_task(name, dense=dense)
        env = make_env("minigrid", name, dense_reward=dense)
        env.reset(seed=0)
        expected = np.empty(len(data.obs))
        for i, (cell, heading, action) in enumerate(zip(data.cells.tolist(), data.headings.tolist(),
                                                        data.action_idx.tolist())):
            env.set_state(tuple(cell), heading)
            expected[i] = env.step(action)[1]
        got = true_reward(task, obs, actions, next_obs)
        assert got.dtype == torch.float64
        assert np.array_equal(got.numpy(), expected), name  # bit for bit, not approximately
        assert (expected > 0).any(), name


def test_decoding_matches_the_grids_own():
    rng = np.random.default_rng(0)
    samples = np.concatenate([rng.uniform(-1.3, 1.3, (2000, 3)),
                              # exact halves between cells round to even, as numpy does
                              (np.arange(-4, 60)[:, None] / 54 * 2 - 1 + np.zeros(3)),
                              [[np.nan, 0, 0], [0, np.inf, 0], [5, -5, 0.25]]]).astype(np.float32)
    assert np.array_equal(decode_obs(torch.from_numpy(samples)).numpy(), decode_batch(samples))
    index = state_index(decode_obs(torch.from_numpy(samples)))
    assert (index[:2000] < LOST).all() and index[-3] == LOST and index[-2] == LOST


def test_true_dynamics_is_the_transition_table():
    data = grid_transitions()
    predicted = true_dynamics(torch.from_numpy(np.array(data.obs)), torch.from_numpy(np.array(data.actions)))
    assert np.array_equal(predicted.numpy(), data.next_obs)
    model = lattice_model(true_dynamics)
    rows = (data.cells[:, 0] * 27 + data.cells[:, 1]) * 4 + data.headings
    truth = [next_state(tuple(c), h, a) for c, h, a in zip(data.cells.tolist(), data.headings.tolist(),
                                                              data.action_idx.tolist())]
    assert model.successor[rows, data.action_idx].tolist() == [(x * 27 + y) * 4 + d for (x, y), d in truth]
    assert (model.successor[LOST] == LOST).all()


# ---------------------------------------------------------------------------------------------------
# the planner with the true dynamics: the evaluation's ceiling
# ---------------------------------------------------------------------------------------------------
def test_planner_reaches_room1s_goal_from_its_start():
    task = get_grid_task("room1")
    planner = LatticePlanner(lattice_model(true_dynamics), task, horizon=SMALL_HORIZON)
    env = make_env("minigrid", "room1")
    env.reset(seed=0)
    obs = env.set_state(task.start, 0)
    generator = torch.Generator().manual_seed(0)
    reached = None
    for t in range(EPISODE_LENGTH):
        state = int(state_index(decode_obs(torch.from_numpy(obs)[None]))[0])
        obs, _, _, _, info = env.step(planner.act(state, EPISODE_LENGTH - t, generator))
        if info["on_goal"]:
            reached = t + 1
            break
    # 7 cells east and 11 south: 18 moves and one turn from facing east.
    assert reached == 19


@pytest.mark.parametrize("name, dense", [("room1", True), ("room1", False), ("room1to3", False),
                                         ("room3to4", True)])
def test_ceiling_is_within_tolerance_of_the_dp_optimum(name, dense):
    (row,) = ceiling([name], episodes=4, readings=["dense" if dense else "sparse"], horizon=SMALL_HORIZON,
                     epsilon=0)
    optimum = task_optimum("minigrid", name, dense)
    assert row["optimum"] == optimum
    assert row["return"] >= (1 - TOLERANCE) * optimum
    assert row["fraction"] == pytest.approx(row["return"] / optimum)


def test_a_short_horizon_cannot_see_a_sparse_goal_in_another_room():
    # The agent's own horizon (5 in minigrid-cpu) sees nothing of room1to3's goal, 12 steps away.
    (row,) = ceiling(["room1to3"], episodes=4, readings=["sparse"], horizon=5, epsilon=0)
    assert row["return"] == 0.0


def test_play_is_reproducible_and_each_episode_independent_of_the_count():
    model = lattice_model(true_dynamics)
    task = get_grid_task("room2")
    four = play(model, task, episodes=4, seed=3, horizon=SMALL_HORIZON, epsilon=0)
    assert np.array_equal(four, play(model, task, episodes=4, seed=3, horizon=SMALL_HORIZON, epsilon=0))
    assert np.array_equal(four[:2], play(model, task, episodes=2, seed=3, horizon=SMALL_HORIZON, epsilon=0))
    # Heading e mod 4: the mean of 4 episodes is the optimum's own average over the start headings.
    assert four.mean() == pytest.approx(task_optimum("minigrid", "room2"))
    # The random steps come from each episode's own stream too.
    noisy = play(model, task, episodes=4, seed=3, horizon=SMALL_HORIZON)
    assert np.array_equal(noisy[:2], play(model, task, episodes=2, seed=3, horizon=SMALL_HORIZON))


def test_with_its_default_random_steps_the_ceiling_stays_above_nine_tenths_of_the_optimum():
    for row in ceiling(episodes=4):
        assert 0.9 <= row["fraction"] <= 1.0 + 1e-9, (row["task"], row["reward"])
        assert row["epsilon"] == DEFAULT_EPSILON


def test_random_steps_free_a_planner_trapped_by_one_wrong_belief():
    # The true dynamics, except that a step forward into a wall or block is believed to go through it. In
    # room 4 the believed shortest route crosses a block: the deterministic planner walks into it at every
    # step for the rest of the episode, while with a few random steps it gets round.
    def walls_believed_open(obs, action):
        following = true_dynamics(obs, action)
        now = decode_obs(obs)
        blocked = (action[:, 2] > 0.5) & (now == decode_obs(following)).all(dim=1)
        out = following.clone()
        for i in torch.nonzero(blocked).flatten().tolist():
            x, y, heading = now[i].tolist()
            dx, dy = ((1, 0), (0, 1), (-1, 0), (0, -1))[heading]
            out[i] = torch.from_numpy(observation((min(max(x + dx, 0), 26), min(max(y + dy, 0), 26)), heading))
        return out

    model, task = lattice_model(walls_believed_open), get_grid_task("room4")
    optimum = task_optimum("minigrid", "room4")
    assert play(model, task, episodes=8, epsilon=0).mean() < 0.01 * optimum
    assert play(model, task, episodes=8).mean() > 0.1 * optimum


def test_a_model_that_lost_the_doors_loses_the_transfers_only():
    # The true dynamics, except that stepping into the opening at the centre leaves the agent where it is:
    # a model that forgot how the rooms connect. Every room stays learnable; no transfer can be done.
    openings = {(13, 12), (12, 13), (14, 13), (13, 14), (13, 13)}

    def doorless(obs, action):
        following = true_dynamics(obs, action)
        cells = [tuple(c) for c in decode_obs(following)[:, :2].tolist()]
        into_door = torch.tensor([c in openings for c in cells])
        return torch.where(into_door[:, None], obs, following)

    model = lattice_model(doorless)
    for name, expected in (("room1", 1.0), ("room4", 1.0), ("room1to2", 0.0), ("room1to3", 0.0)):
        task = get_grid_task(name)
        returns = play(model, task, episodes=4, horizon=SMALL_HORIZON, epsilon=0)
        assert returns.mean() / task_optimum("minigrid", name) == pytest.approx(expected), name


# ---------------------------------------------------------------------------------------------------
# the matrix of a run
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_matrix_has_one_row_per_stage_and_task_and_is_reproducible(smoke_run, tmp_path):
    torch_before = torch.get_rng_state()
    numpy_before = np.random.get_state()[1].copy()
    rows = zero_shot_matrix(smoke_run, episodes=2, seed=5)
    assert torch.equal(torch.get_rng_state(), torch_before)
    assert np.array_equal(np.random.get_state()[1], numpy_before)

    tasks = [*TRAINING, *TRANSFERS]
    assert default_tasks(TRAINING) == tasks
    assert [(r["stage"], r["task"]) for r in rows] == [(s, t) for s in range(1, 5) for t in tasks]
    for row in rows:
        assert set(row) == set(CSV_COLUMNS)
        assert row["stage_task"] == TRAINING[row["stage"] - 1]
        assert row["reward"] == ("dense" if row["task"] in TRAINING else "sparse")
        assert row["method"] == "continual" and row["seed"] == 1
        assert math.isfinite(row["return"]) and row["return_std"] >= 0
        assert row["fraction"] == pytest.approx(row["return"] / row["optimum"])
    assert sum(is_paper_case(r) for r in rows) == 4

    assert zero_shot_matrix(smoke_run, episodes=2, seed=5) == rows

    path = write_zero_shot_csv(rows, tmp_path / "zero_shot.csv")
    back = read_csv(path)
    assert list(back[0]) == list(CSV_COLUMNS) and len(back) == len(rows)
    assert float(back[3]["return"]) == rows[3]["return"]

    stages, columns, R = return_matrix(rows)
    assert stages == [1, 2, 3, 4] and columns == tasks and R.shape == (4, 7)
    (metrics,) = matrix_metrics(rows)
    assert metrics["reward"] == "dense" and metrics["stages"] == 4
    assert metrics["acc"] == pytest.approx(R[3, :4].mean())
    table = format_table(rows)
    assert len(table) == 1 + 4 and "room1to3" in table[0] and "*" in table[3]


@pytest.mark.slow
def test_matrix_plans_with_the_models_predictions(smoke_run):
    path = smoke_run / "checkpoints" / "task4_room4.pt"
    predictor = load_world_model(path)
    model = lattice_model(model_dynamics(predictor.world_model))
    data = grid_transitions()
    rows = (data.cells[:, 0] * 27 + data.cells[:, 1]) * 4 + data.headings
    expected = predictor.predict(data.obs, data.actions)
    assert np.array_equal(model.predicted[rows, data.action_idx], expected)
    # A stage's rows with both readings and chosen tasks, for the model after task 4 only.
    rows = zero_shot_matrix(smoke_run, tasks=["room4", "room3to4"], episodes=1, readings=["dense", "sparse"])
    assert [(r["task"], r["reward"]) for r in rows if r["stage"] == 4] == [
        ("room4", "dense"), ("room4", "sparse"), ("room3to4", "dense"), ("room3to4", "sparse")]


@pytest.mark.slow
def test_bad_runs_and_arguments_are_one_line_errors(smoke_run, tmp_path):
    other = tmp_path / "cheetah-run"
    write_run_config(other, load_config("cheetah-cpu"))
    for run, tasks, words in ((other, None, "needs a tabular domain"),
                              (tmp_path / "nowhere", None, "does not exist"),
                              (smoke_run, ["room9"], "unknown grid task")):
        with pytest.raises(ZeroShotError) as err:
            zero_shot_matrix(run, tasks=tasks, episodes=1)
        assert words in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ZeroShotError, match="readings"):
        zero_shot_matrix(smoke_run, readings=["shaped"])
    with pytest.raises(ZeroShotError, match="episodes"):
        ceiling(episodes=0)
    assert observation((1, 1), 0).dtype == np.float32


@pytest.mark.slow
def test_drago_eval_zero_shot_writes_each_runs_matrix_and_prints_its_metrics(smoke_run, tmp_path, capsys):
    from drago import cli

    assert cli.main(["eval", "zero-shot", str(smoke_run), "--episodes", "1", "--out", str(tmp_path / "all.csv")]) == 0
    out = capsys.readouterr().out
    written = read_csv(smoke_run / "zero_shot.csv")
    assert [(r["stage"], r["task"]) for r in written] == [(str(s), t) for s in range(1, 5)
                                                         for t in (*TRAINING, *TRANSFERS)]
    assert read_csv(tmp_path / "all.csv") == written
    again = zero_shot_matrix(smoke_run, episodes=1)
    assert [float(r["fraction"]) for r in written] == pytest.approx([r["fraction"] for r in again])
    (metrics,) = matrix_metrics(again)
    assert f"ACC {metrics['acc']:.3f}" in out and "room1to2" in out and f"wrote {smoke_run / 'zero_shot.csv'}" in out


def test_drago_eval_zero_shot_refuses_a_run_of_another_domain_in_one_line(tmp_path, capsys):
    from drago import cli

    other = tmp_path / "cheetah-run"
    write_run_config(other, load_config("cheetah-cpu"))
    assert cli.main(["eval", "zero-shot", str(other)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drago: error: ") and "needs a tabular domain" in err and len(err.splitlines()) == 1
