"""The 27x27 four-rooms MiniGrid world of DRAGO (paper Appendix C).

The map is fixed: outer walls, an inner wall cross at x=13 / y=13 with a
plus-shaped five-cell opening at the centre, and 20 coloured blocks that are
impassable like walls. One module-level table of blocked cells is the single
source of truth for movement; the minigrid grid is built from the same table
and is kept for rendering only.

Coordinates are minigrid's: ``x`` is the column (left to right), ``y`` the row
(top to bottom). Headings follow minigrid's ``DIR_TO_VEC``: 0 east (+x),
1 south (+y), 2 west (-x), 3 north (-y).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from typing import Any

import numpy as np
from gymnasium import spaces
from minigrid.core.grid import Grid
from minigrid.core.mission import MissionSpace
from minigrid.core.world_object import Goal, Wall
from minigrid.minigrid_env import MiniGridEnv

from drago.envs.tasks import GRID_SEQUENCES, GRID_TASKS, GridTask, get_grid_task

__all__ = [
    "SIZE",
    "EPISODE_LENGTH",
    "GOAL_RADIUS",
    "CENTRE",
    "BLOCKS",
    "OPENINGS",
    "ROOM_BOUNDS",
    "TRAINING_GOALS",
    "ACTION_NAMES",
    "FourRoomsEnv",
    "grid_reward",
    "observation",
    "decode_observation",
    "traversable_cells",
    "is_traversable",
    "ascii_map",
    "next_state",
    "optimal_returns",
    "optimal_return",
]

SIZE = 27
EPISODE_LENGTH = 100
GOAL_RADIUS = 12
CENTRE = 13
ACTION_NAMES = ("left", "right", "forward")

BLOCKS: dict[str, tuple[tuple[int, int], ...]] = {
    "blue": ((6, 6), (20, 3), (9, 16), (20, 20)),
    "red": ((10, 9), (22, 10), (4, 19), (25, 23)),
    "purple": ((10, 4), (17, 5), (7, 23), (16, 17)),
    "yellow": ((5, 2), (17, 2), (4, 8), (20, 8), (4, 15), (23, 16), (5, 22), (18, 23)),
}

# The openings left in the inner cross; together they form a plus at the centre.
OPENINGS: tuple[tuple[int, int], ...] = ((13, 12), (12, 13), (14, 13), (13, 14), (13, 13))

# Room interiors as (x_lo, x_hi, y_lo, y_hi), bounds inclusive.
ROOM_BOUNDS: dict[int, tuple[int, int, int, int]] = {
    1: (1, 12, 1, 12),
    2: (14, 25, 1, 12),
    3: (1, 12, 14, 25),
    4: (14, 25, 14, 25),
}

TRAINING_GOALS: tuple[tuple[int, int], ...] = tuple(
    GRID_TASKS[name].goal for name in GRID_SEQUENCES["fourrooms"]
)

# minigrid's DIR_TO_VEC as plain tuples: indexing tuples is much cheaper than numpy.
_DIR_TO_VEC: tuple[tuple[int, int], ...] = ((1, 0), (0, 1), (-1, 0), (0, -1))
_LEFT, _RIGHT, _FORWARD = 0, 1, 2


def _wall_cells() -> frozenset[tuple[int, int]]:
    walls = set()
    for i in range(SIZE):
        walls.update({(i, 0), (i, SIZE - 1), (0, i), (SIZE - 1, i)})
        walls.update({(CENTRE, i), (i, CENTRE)})
    return frozenset(walls.difference(OPENINGS))


_WALLS: frozenset[tuple[int, int]] = _wall_cells()
_BLOCK_COLOUR: dict[tuple[int, int], str] = {
    pos: colour for colour, cells in BLOCKS.items() for pos in cells
}
# Single source of truth for movement, used by both the env and next_state.
_BLOCKED: frozenset[tuple[int, int]] = _WALLS | frozenset(_BLOCK_COLOUR)


def is_traversable(pos: tuple[int, int]) -> bool:
    """Whether the agent can stand on ``pos`` (inside the map, not a wall or block)."""
    x, y = pos
    return 0 <= x < SIZE and 0 <= y < SIZE and (x, y) not in _BLOCKED


def traversable_cells() -> list[tuple[int, int]]:
    """All cells the agent can occupy (goal tiles included), row-major order.

    Returns:
        561 ``(x, y)`` cells, sorted by ``y`` then ``x``.
    """
    return [(x, y) for y in range(SIZE) for x in range(SIZE) if (x, y) not in _BLOCKED]


def ascii_map() -> list[str]:
    """The training layout as text, identical to the official code's render.

    Returns:
        27 rows of 27 characters: ``#`` wall, ``.`` free, ``B/R/P/Y`` blocks by
        colour, ``G`` training goal tiles.
    """
    rows = []
    for y in range(SIZE):
        row = []
        for x in range(SIZE):
            if (x, y) in _WALLS:
                row.append("#")
            elif (x, y) in _BLOCK_COLOUR:
                row.append(_BLOCK_COLOUR[(x, y)][0].upper())
            elif (x, y) in TRAINING_GOALS:
                row.append("G")
            else:
                row.append(".")
        rows.append("".join(row))
    return rows


def next_state(pos: tuple[int, int], direction: int, action: int) -> tuple[tuple[int, int], int]:
    """Deterministic transition on the fixed map.

    Args:
        pos: Current cell ``(x, y)``.
        direction: Current heading in {0, 1, 2, 3}.
        action: 0 turn left, 1 turn right, 2 forward.

    Returns:
        The new ``(pos, direction)``; forward into a wall or block leaves the
        agent where it is.
    """
    if action == _FORWARD:
        dx, dy = _DIR_TO_VEC[direction]
        target = (pos[0] + dx, pos[1] + dy)
        if target in _BLOCKED:
            return pos, direction
        return target, direction
    if action == _LEFT:
        return pos, (direction - 1) % 4
    if action == _RIGHT:
        return pos, (direction + 1) % 4
    raise ValueError(f"action must be 0, 1 or 2, got {action!r}")


def grid_reward(
    prev_pos: tuple[int, int], pos: tuple[int, int], goal: tuple[int, int], dense: bool
) -> float:
    """Reward for moving from ``prev_pos`` to ``pos`` (paper Appendix C).

    Args:
        prev_pos: Agent cell before the step.
        pos: Agent cell after the step.
        goal: The task's goal cell.
        dense: Dense (shaped) reward if True, sparse otherwise.

    Returns:
        0 unless ``pos`` passes the same-quadrant gate. Sparse: 1 on the goal.
        Dense: ``max(0, 1 - d/12)`` on strictly distance-reducing steps or on
        the goal, plus 2 on the goal.
    """
    px, py = pos
    gx, gy = goal
    # The original code's gate: strict in x, non-strict in y, so row y=13
    # (with its door cells) counts and column x=13 never does.
    if not ((px - CENTRE) * (gx - CENTRE) > 0 and (py - CENTRE) * (gy - CENTRE) >= 0):
        return 0.0
    on_goal = px == gx and py == gy
    if not dense:
        return 1.0 if on_goal else 0.0
    # Squared integer distances make the "strictly closer" test exact.
    d2 = (px - gx) ** 2 + (py - gy) ** 2
    prev_d2 = (prev_pos[0] - gx) ** 2 + (prev_pos[1] - gy) ** 2
    reward = 0.0
    if on_goal or d2 < prev_d2:
        reward = max(0.0, 1.0 - math.sqrt(d2) / GOAL_RADIUS)
    if on_goal:
        reward += 2.0
    return reward


def observation(pos: tuple[int, int], direction: int) -> np.ndarray:
    """Encode a state as the 3-dim observation ``(2x/27-1, 2y/27-1, 2d/4-1)``.

    Args:
        pos: Agent cell ``(x, y)``.
        direction: Heading in {0, 1, 2, 3}.

    Returns:
        float32 array of shape (3,).
    """
    # Division by 27 (not 26) matches the original code.
    return np.array(
        (2.0 * pos[0] / SIZE - 1.0, 2.0 * pos[1] / SIZE - 1.0, 2.0 * direction / 4.0 - 1.0),
        dtype=np.float32,
    )


def decode_observation(obs: Sequence[float] | np.ndarray) -> tuple[int, int, int]:
    """Map a (possibly predicted, noisy) observation to the nearest state.

    Args:
        obs: Array-like of shape (3,).

    Returns:
        ``(x, y, dir)`` rounded to the nearest integers and clipped to
        ``[0, 26]`` for positions and ``[0, 3]`` for the heading.
    """
    o = np.asarray(obs, dtype=np.float64).reshape(3)
    x = int(np.clip(np.rint((o[0] + 1.0) * SIZE / 2.0), 0, SIZE - 1))
    y = int(np.clip(np.rint((o[1] + 1.0) * SIZE / 2.0), 0, SIZE - 1))
    d = int(np.clip(np.rint((o[2] + 1.0) * 2.0), 0, 3))
    return x, y, d


@lru_cache(maxsize=1)
def _transition_table() -> tuple[tuple[tuple[int, int], ...], np.ndarray]:
    """States (cell, heading) in a fixed order and their successor indices."""
    cells = traversable_cells()
    index = {(cell, d): i for i, (cell, d) in enumerate((c, d) for c in cells for d in range(4))}
    states = tuple(index)
    successor = np.empty((len(states), 3), dtype=np.int64)
    for i, (cell, d) in enumerate(states):
        for a in range(3):
            successor[i, a] = index[next_state(cell, d, a)]
    successor.setflags(write=False)
    return states, successor


def optimal_returns(task: GridTask, horizon: int = EPISODE_LENGTH) -> np.ndarray:
    """Optimal undiscounted return from ``task.start`` by finite-horizon DP.

    Args:
        task: The task (start, goal and reward type are used).
        horizon: Episode length in steps.

    Returns:
        float64 array of shape (4,): the optimal return for each start heading.
    """
    states, successor = _transition_table()
    cells = [cell for cell, _ in states]
    reward = np.array(
        [
            [grid_reward(cells[i], cells[successor[i, a]], task.goal, task.dense) for a in range(3)]
            for i in range(len(states))
        ]
    )
    value = np.zeros(len(states))
    for _ in range(horizon):
        value = (reward + value[successor]).max(axis=1)
    index = {s: i for i, s in enumerate(states)}
    return np.array([value[index[(tuple(task.start), d)]] for d in range(4)])


def optimal_return(task: GridTask, horizon: int = EPISODE_LENGTH) -> float:
    """Optimal return from ``task.start`` averaged over the 4 uniform start headings."""
    return float(optimal_returns(task, horizon).mean())


class FourRoomsEnv(MiniGridEnv):
    """DRAGO's four-rooms world with a 3-dim vector observation.

    The agent starts at ``task.start`` with a uniformly random heading, acts
    with a one-hot (argmax) or integer action, and is paid by
    :func:`grid_reward`. Episodes last exactly 100 steps: reaching the goal
    never terminates, so the agent can keep collecting goal reward.
    """

    def __init__(
        self,
        task: GridTask,
        render_mode: str | None = None,
        goal_positions: Sequence[tuple[int, int]] | None = None,
    ) -> None:
        """Create the env.

        Args:
            task: Start, goal and reward type.
            render_mode: None, ``"rgb_array"`` or ``"human"``.
            goal_positions: Cells that get a (visual) goal tile; defaults to
                the four training goals plus the task's goal.
        """
        for what, cell in (("start", task.start), ("goal", task.goal)):
            if not is_traversable(tuple(cell)):
                raise ValueError(f"task {task.name!r}: {what} {tuple(cell)} is not a free cell")
        self.task = task
        self.goal: tuple[int, int] = (int(task.goal[0]), int(task.goal[1]))
        self.dense = bool(task.dense)
        if goal_positions is None:
            goal_positions = (*TRAINING_GOALS, self.goal)
        self.goal_positions: tuple[tuple[int, int], ...] = tuple(
            dict.fromkeys((int(x), int(y)) for x, y in goal_positions)
        )
        super().__init__(
            mission_space=MissionSpace(mission_func=self._gen_mission),
            grid_size=SIZE,
            max_steps=EPISODE_LENGTH,
            see_through_walls=True,
            agent_view_size=5,
            render_mode=render_mode,
        )
        self.action_space = spaces.Box(0.0, 1.0, (3,), np.float32)
        self.observation_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        # The map never changes, so it is built once rather than on every reset.
        self._gen_grid(SIZE, SIZE)
        self.step_count = 0

    @staticmethod
    def _gen_mission() -> str:
        return "get to the green goal square"

    def _gen_grid(self, width: int, height: int) -> None:
        grid = Grid(width, height)
        for x, y in _WALLS:
            grid.set(x, y, Wall())
        for (x, y), colour in _BLOCK_COLOUR.items():
            grid.set(x, y, Wall(colour))
        for x, y in self.goal_positions:
            if (x, y) not in _BLOCKED:
                grid.set(x, y, Goal())
        x, y = self.task.start
        grid.set(x, y, None)
        self.grid = grid
        self.agent_pos = (int(x), int(y))
        self.agent_dir = 0
        self.mission = self._gen_mission()

    def _info(self) -> dict[str, Any]:
        return {"pos": self.agent_pos, "dir": self.agent_dir, "on_goal": self.agent_pos == self.goal}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode at ``task.start`` with a random heading.

        Args:
            seed: Seeds the env's RNG (heading draws) when given.
            options: Unused.

        Returns:
            ``(obs, info)``.
        """
        # Bypass MiniGridEnv.reset: it regenerates the grid and builds the image observation.
        super(MiniGridEnv, self).reset(seed=seed)
        self.agent_pos = (int(self.task.start[0]), int(self.task.start[1]))
        self.agent_dir = int(self.np_random.integers(0, 4))
        self.carrying = None
        self.step_count = 0
        if self.render_mode == "human":
            self.render()
        return observation(self.agent_pos, self.agent_dir), self._info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Advance one step.

        Args:
            action: An int in {0, 1, 2} or a length-3 vector (its argmax is taken).

        Returns:
            ``(obs, reward, terminated, truncated, info)``; ``terminated`` is
            always False and ``truncated`` is True from step 100 on.
        """
        if isinstance(action, (int, np.integer)):
            a = int(action)
        else:
            vec = np.asarray(action)
            if vec.shape != (3,):
                raise ValueError(f"action must be an int or a length-3 vector, got shape {vec.shape}")
            a = int(vec.argmax())
        prev_pos = self.agent_pos
        self.agent_pos, self.agent_dir = next_state(prev_pos, self.agent_dir, a)
        self.step_count += 1
        reward = grid_reward(prev_pos, self.agent_pos, self.goal, self.dense)
        truncated = self.step_count >= self.max_steps
        if self.render_mode == "human":
            self.render()
        return observation(self.agent_pos, self.agent_dir), reward, False, truncated, self._info()

    def set_state(self, pos: tuple[int, int], direction: int) -> np.ndarray:
        """Put the agent at ``pos`` facing ``direction`` (the step counter is untouched).

        Args:
            pos: A traversable cell ``(x, y)``.
            direction: Heading in {0, 1, 2, 3}.

        Returns:
            The observation of the new state.

        Raises:
            ValueError: If ``pos`` is a wall, a block or off the map, or the
                heading is invalid.
        """
        cell = (int(pos[0]), int(pos[1]))
        if not is_traversable(cell):
            raise ValueError(f"cell {cell} is a wall, a block or off the map")
        if int(direction) not in (0, 1, 2, 3):
            raise ValueError(f"direction must be 0, 1, 2 or 3, got {direction!r}")
        self.agent_pos = cell
        self.agent_dir = int(direction)
        return observation(self.agent_pos, self.agent_dir)


def make_fourrooms(task: str = "room1", dense_reward: bool | None = None, render_mode: str | None = None) -> FourRoomsEnv:
    """Entry point of the gymnasium id ``MiniGrid-FourRooms-New``: a task by name."""
    return FourRoomsEnv(get_grid_task(task, dense=dense_reward), render_mode=render_mode)
