"""Behavioural tests of the four-rooms world against the paper's numbers (paper Appendix C)."""

from __future__ import annotations

import numpy as np
import pytest

from drago.envs.fourrooms import (
    BLOCKS,
    EPISODE_LENGTH,
    FourRoomsEnv,
    ascii_map,
    decode_observation,
    grid_reward,
    next_state,
    observation,
    optimal_return,
    optimal_returns,
    traversable_cells,
)
from drago.envs.tasks import GRID_SEQUENCES, GRID_TASKS, GridTask, get_grid_task

# The training layout as an ASCII render (paper Appendix C), row labels stripped.
SPEC_MAP = [
    "###########################",
    "#............#............#",
    "#....Y.......#...Y........#",
    "#............#......B.....#",
    "#.........P..#............#",
    "#............#...P........#",
    "#.....B......#............#",
    "#............#............#",
    "#...Y........#......Y.....#",
    "#.........R..#............#",
    "#............#........R...#",
    "#............#............#",
    "#.......G........G........#",
    "############...############",
    "#.........................#",
    "#...Y........#....G.......#",
    "#........B...#.........Y..#",
    "#............#..P.........#",
    "#............#............#",
    "#...R.......G#............#",
    "#............#......B.....#",
    "#............#............#",
    "#....Y.......#............#",
    "#......P.....#....Y......R#",
    "#............#............#",
    "#............#............#",
    "###########################",
]

CENTRE_OPENINGS = [(13, 12), (12, 13), (14, 13), (13, 14), (13, 13)]
EAST, SOUTH, WEST, NORTH = 0, 1, 2, 3
LEFT, RIGHT, FORWARD = 0, 1, 2


@pytest.fixture
def room1_env() -> FourRoomsEnv:
    return FourRoomsEnv(get_grid_task("room1"))


# --- map -----------------------------------------------------------------


def test_ascii_map_matches_spec() -> None:
    assert ascii_map() == SPEC_MAP


def test_traversable_cells() -> None:
    cells = traversable_cells()
    assert len(cells) == 561
    assert len(set(cells)) == 561
    for cell in CENTRE_OPENINGS:
        assert cell in cells
    for x, y in cells:
        assert SPEC_MAP[y][x] in ".G"


def test_block_table_is_the_spec_table() -> None:
    assert sum(len(v) for v in BLOCKS.values()) == 20
    letters = {"blue": "B", "red": "R", "purple": "P", "yellow": "Y"}
    for colour, cells in BLOCKS.items():
        for x, y in cells:
            assert SPEC_MAP[y][x] == letters[colour]


def test_centre_openings_are_passable_in_env(room1_env: FourRoomsEnv) -> None:
    env = room1_env
    env.reset(seed=0)
    # Walk west to east along row 13 and north to south along column 13.
    env.set_state((12, 13), EAST)
    for expected in [(13, 13), (14, 13)]:
        *_, info = env.step(FORWARD)
        assert info["pos"] == expected
    env.set_state((13, 12), SOUTH)
    for expected in [(13, 13), (13, 14)]:
        *_, info = env.step(FORWARD)
        assert info["pos"] == expected


@pytest.mark.parametrize("block", [c for cells in BLOCKS.values() for c in cells])
def test_every_block_is_impassable_in_env(room1_env: FourRoomsEnv, block: tuple[int, int]) -> None:
    env = room1_env
    env.reset(seed=0)
    attempts = 0
    for direction, (dx, dy) in enumerate([(1, 0), (0, 1), (-1, 0), (0, -1)]):
        neighbour = (block[0] - dx, block[1] - dy)
        if neighbour not in traversable_cells():
            continue
        env.set_state(neighbour, direction)
        obs, _, _, _, info = env.step(np.array([0.0, 0.1, 0.9], dtype=np.float32))
        assert info["pos"] == neighbour
        assert info["dir"] == direction
        np.testing.assert_array_equal(obs, observation(neighbour, direction))
        attempts += 1
    assert attempts > 0


def test_set_state_rejects_walls_and_blocks(room1_env: FourRoomsEnv) -> None:
    for cell in [(0, 0), (13, 5), (5, 13), (6, 6), (25, 23)]:
        with pytest.raises(ValueError):
            room1_env.set_state(cell, 0)


def test_rgb_render_works() -> None:
    env = FourRoomsEnv(get_grid_task("room2"), render_mode="rgb_array")
    env.reset(seed=1)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3
    assert frame.shape[0] == frame.shape[1] > 0


# --- observation -----------------------------------------------------------


@pytest.mark.parametrize(
    ("pos", "direction", "expected"),
    [
        ((1, 1), 0, (2 / 27 - 1, 2 / 27 - 1, -1.0)),
        ((25, 25), 3, (50 / 27 - 1, 50 / 27 - 1, 0.5)),
        ((13, 13), 2, (26 / 27 - 1, 26 / 27 - 1, 0.0)),
        ((8, 12), 1, (16 / 27 - 1, 24 / 27 - 1, -0.5)),
    ],
)
def test_observation_formula(pos: tuple[int, int], direction: int, expected: tuple[float, ...]) -> None:
    obs = observation(pos, direction)
    assert obs.dtype == np.float32 and obs.shape == (3,)
    np.testing.assert_allclose(obs, expected, atol=1e-6)


def test_observation_range() -> None:
    obs = np.array([observation(c, d) for c in traversable_cells() for d in range(4)])
    np.testing.assert_allclose(obs[:, 0].min(), -0.926, atol=1e-3)
    np.testing.assert_allclose(obs[:, 0].max(), 0.852, atol=1e-3)
    assert set(np.round(obs[:, 2], 6)) == {-1.0, -0.5, 0.0, 0.5}


def test_decode_round_trips_all_states() -> None:
    states = [(c, d) for c in traversable_cells() for d in range(4)]
    assert len(states) == 2244
    rng = np.random.default_rng(0)
    for (x, y), d in states:
        obs = observation((x, y), d)
        assert decode_observation(obs) == (x, y, d)
        # Small prediction errors still decode to the same state.
        noisy = obs + rng.uniform(-0.03, 0.03, size=3).astype(np.float32)
        assert decode_observation(noisy) == (x, y, d)


def test_decode_clips() -> None:
    assert decode_observation([-3.0, 5.0, 2.0]) == (0, 26, 3)
    assert decode_observation([1.0, -1.0, -1.7]) == (26, 0, 0)


# --- reward ----------------------------------------------------------------


def test_quadrant_gate_edges() -> None:
    goal = (8, 12)  # room 1; the door cell (12,13) is 4.12 away, inside radius 12
    # Row y=13 counts whenever the x-test passes: the door (12,13) pays shaping.
    assert grid_reward((12, 14), (12, 13), goal, True) == pytest.approx(1 - np.hypot(4, 1) / 12)
    # Column x=13 never counts, even when it is closer to the goal.
    assert grid_reward((14, 13), (13, 13), goal, True) == 0.0
    assert grid_reward((13, 13), (13, 12), goal, True) == 0.0
    # The other room's side fails the gate.
    assert grid_reward((14, 11), (15, 11), (17, 12), True) == pytest.approx(1 - np.hypot(2, 1) / 12)
    assert grid_reward((11, 12), (12, 12), (17, 12), True) == 0.0  # closer, but room 1
    # Door (14,13) counts for the room-2 goal (17,12) but not for room 4's (18,15).
    assert grid_reward((14, 14), (14, 13), (17, 12), True) == pytest.approx(1 - np.hypot(3, 1) / 12)
    assert grid_reward((13, 13), (14, 13), (18, 15), True) == pytest.approx(1 - np.hypot(4, 2) / 12)
    # For a goal below the cross, row 13 still counts (non-strict y-test)...
    assert grid_reward((12, 12), (12, 13), (12, 19), True) == pytest.approx(1 - 6 / 12)
    # ... but row 12 does not.
    assert grid_reward((12, 11), (12, 12), (12, 19), True) == 0.0


def test_shaping_only_on_strictly_closer_steps() -> None:
    goal = (8, 12)
    closer = grid_reward((5, 12), (6, 12), goal, True)
    assert closer == pytest.approx(1 - 2 / 12)
    assert grid_reward((6, 12), (5, 12), goal, True) == 0.0  # moving away
    assert grid_reward((6, 12), (6, 12), goal, True) == 0.0  # turning / bumping
    # Equal distance (sideways across the goal column) pays nothing.
    assert grid_reward((7, 11), (9, 11), goal, True) == 0.0


def test_goal_radius() -> None:
    goal = (8, 12)
    # d = 12 exactly: max(0, 1 - 1) = 0; farther cells are also 0.
    assert grid_reward((8, 1), (8, 0), goal, True) == 0.0  # not traversable, but pure maths
    assert grid_reward((1, 1), (2, 1), goal, True) == 0.0  # d ~ 12.5
    assert grid_reward((9, 1), (8, 1), goal, True) == pytest.approx(1 - 11 / 12)


def test_goal_pays_three_dense_one_sparse() -> None:
    goal = (8, 12)
    assert grid_reward((7, 12), (8, 12), goal, True) == pytest.approx(3.0)
    assert grid_reward((8, 12), (8, 12), goal, True) == pytest.approx(3.0)
    assert grid_reward((7, 12), (8, 12), goal, False) == 1.0
    assert grid_reward((8, 12), (8, 12), goal, False) == 1.0
    assert grid_reward((6, 12), (7, 12), goal, False) == 0.0
    assert grid_reward((8, 11), (8, 12), (17, 12), False) == 0.0  # not this task's goal


def test_turning_on_goal_keeps_paying_in_env() -> None:
    for dense, per_step in [(True, 3.0), (False, 1.0)]:
        env = FourRoomsEnv(get_grid_task("room1", dense=dense))
        env.reset(seed=0)
        env.set_state((8, 12), EAST)
        for action in [LEFT, RIGHT, LEFT, LEFT, LEFT]:
            _, reward, terminated, _, info = env.step(action)
            assert reward == pytest.approx(per_step)
            assert info["on_goal"] and not terminated


# --- optimal returns (exact DP numbers of the paper's grid, Appendix C) ----------------------


@pytest.mark.parametrize(
    ("name", "dense", "expected"),
    [
        ("room1", True, 250.9),
        ("room2", True, 247.0),
        ("room3", True, 253.3),
        ("room4", True, 250.4),
        ("room1", False, 81.5),
        ("room2", False, 80.0),
        ("room3", False, 82.0),
        ("room4", False, 81.0),
        ("room1to2", False, 88.0),
        ("room1to3", False, 88.0),
        ("room3to4", False, 88.0),
        ("room1to2", True, 266.5),
        ("room1to3", True, 267.2),
        ("room3to4", True, 266.5),
    ],
)
def test_optimal_returns_match_spec(name: str, dense: bool, expected: float) -> None:
    task = get_grid_task(name, dense=dense)
    per_heading = optimal_returns(task)
    assert per_heading.shape == (4,)
    assert optimal_return(task) == pytest.approx(expected, abs=0.05)


def test_optimal_return_achieved_by_greedy_rollout_in_env() -> None:
    """Following the DP policy in the real env collects exactly the DP value."""
    task = get_grid_task("room1")
    cells = traversable_cells()
    states = [(c, d) for c in cells for d in range(4)]
    index = {s: i for i, s in enumerate(states)}
    succ = np.array([[index[next_state(c, d, a)] for a in range(3)] for c, d in states])
    rew = np.array(
        [[grid_reward(c, next_state(c, d, a)[0], task.goal, task.dense) for a in range(3)] for c, d in states]
    )
    values = [np.zeros(len(states))]
    for _ in range(EPISODE_LENGTH):
        values.append((rew + values[-1][succ]).max(axis=1))
    env = FourRoomsEnv(task)
    expected = optimal_returns(task)
    for seed in range(8):
        _, info = env.reset(seed=seed)
        start_dir = info["dir"]
        total = 0.0
        for t in range(EPISODE_LENGTH):
            s = index[(info["pos"], info["dir"])]
            action = int(np.argmax(rew[s] + values[EPISODE_LENGTH - t - 1][succ[s]]))
            _, reward, _, _, info = env.step(action)
            total += reward
        assert total == pytest.approx(expected[start_dir])


# --- env vs pure functions --------------------------------------------------


def test_env_matches_pure_functions_on_random_rollouts() -> None:
    rng = np.random.default_rng(123)
    for name in ["room1", "room2", "room3", "room4", "room1to3"]:
        for dense in (True, False):
            task = get_grid_task(name, dense=dense)
            env = FourRoomsEnv(task)
            obs, info = env.reset(seed=int(rng.integers(1 << 30)))
            pos, direction = info["pos"], info["dir"]
            assert pos == task.start
            np.testing.assert_array_equal(obs, observation(pos, direction))
            for t in range(EPISODE_LENGTH):
                # Mix the two action formats: plain ints and 3-vectors.
                if t % 2:
                    action = int(rng.integers(3))
                    env_action: int | np.ndarray = action
                else:
                    env_action = rng.random(3).astype(np.float32)
                    action = int(np.argmax(env_action))
                obs, reward, terminated, truncated, info = env.step(env_action)
                new_pos, new_dir = next_state(pos, direction, action)
                assert (info["pos"], info["dir"]) == (new_pos, new_dir)
                assert reward == grid_reward(pos, new_pos, task.goal, task.dense)
                np.testing.assert_array_equal(obs, observation(new_pos, new_dir))
                assert info["on_goal"] == (new_pos == task.goal)
                assert terminated is False
                assert truncated == (t == EPISODE_LENGTH - 1)
                pos, direction = new_pos, new_dir


def test_episode_is_exactly_100_steps_and_never_terminates() -> None:
    env = FourRoomsEnv(get_grid_task("room1"))
    env.reset(seed=0)
    env.set_state((8, 12), EAST)  # sitting on the goal must not end the episode
    flags = [env.step(LEFT)[2:4] for _ in range(EPISODE_LENGTH)]
    assert all(term is False for term, _ in flags)
    assert [trunc for _, trunc in flags] == [False] * (EPISODE_LENGTH - 1) + [True]


def test_spaces() -> None:
    env = FourRoomsEnv(get_grid_task("room3"))
    assert env.action_space.shape == (3,) and env.action_space.dtype == np.float32
    assert env.observation_space.shape == (3,) and env.observation_space.dtype == np.float32
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)


def test_seeded_reset_is_reproducible() -> None:
    def headings(seed: int) -> list[int]:
        env = FourRoomsEnv(get_grid_task("room1"))
        first = env.reset(seed=seed)[1]["dir"]
        return [first] + [env.reset()[1]["dir"] for _ in range(11)]

    assert headings(7) == headings(7)
    assert headings(7) != headings(8)
    assert set(headings(7) + headings(8)) == {0, 1, 2, 3}


# --- task catalogue ---------------------------------------------------------


def test_task_catalogue() -> None:
    assert GRID_SEQUENCES["fourrooms"] == ("room1", "room2", "room3", "room4")
    expected = {
        "room1": ((1, 1), (8, 12), True),
        "room2": ((25, 1), (17, 12), True),
        "room3": ((1, 25), (12, 19), True),
        "room4": ((25, 25), (18, 15), True),
        "room1to2": ((11, 8), (14, 9), False),
        "room1to3": ((8, 11), (9, 14), False),
        "room3to4": ((11, 18), (14, 17), False),
    }
    assert {n: (t.start, t.goal, t.dense) for n, t in GRID_TASKS.items()} == expected
    for task in GRID_TASKS.values():
        assert isinstance(task, GridTask)
        assert "\n" not in task.description and task.description


def test_get_grid_task_dense_override() -> None:
    assert get_grid_task("room1to2").dense is False
    assert get_grid_task("room1to2", dense=True).dense is True
    assert get_grid_task("room1", dense=False).dense is False
    assert get_grid_task("room1", dense=None) == GRID_TASKS["room1"]
    assert GRID_TASKS["room1"].dense is True  # the catalogue is not mutated


def test_get_grid_task_unknown_name() -> None:
    with pytest.raises(ValueError) as excinfo:
        get_grid_task("nope")
    message = str(excinfo.value)
    assert "\n" not in message
    assert "'nope'" in message
    for name in GRID_TASKS:
        assert name in message
