"""Task catalogue for the four-rooms MiniGrid world (spec §1.1.4).

Tasks are plain data: a start cell, a goal cell and the reward type. The
world itself lives in :mod:`drago.envs.fourrooms`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

__all__ = ["GridTask", "GRID_TASKS", "GRID_SEQUENCES", "get_grid_task"]


@dataclass(frozen=True)
class GridTask:
    """One four-rooms task.

    Attributes:
        name: Catalogue name, e.g. ``"room1"``.
        start: Start cell ``(x, y)`` in minigrid coordinates (x column, y row).
        goal: Goal cell ``(x, y)``; the only cell that pays goal reward.
        dense: True for the shaped (dense) reward, False for the sparse one.
        description: One line shown by ``drago list``.
    """

    name: str
    start: tuple[int, int]
    goal: tuple[int, int]
    dense: bool
    description: str


def _task(name: str, start: tuple[int, int], goal: tuple[int, int], dense: bool, what: str) -> GridTask:
    # The reward type is kept out of the text because ``get_grid_task`` can override it.
    return GridTask(name, start, goal, dense, f"{what}: {start} -> {goal}")


GRID_TASKS: dict[str, GridTask] = {
    t.name: t
    for t in (
        # Continual training tasks: one per room, corner start, dense reward.
        _task("room1", (1, 1), (8, 12), True, "training task 1, top-left room"),
        _task("room2", (25, 1), (17, 12), True, "training task 2, top-right room"),
        _task("room3", (1, 25), (12, 19), True, "training task 3, bottom-left room"),
        _task("room4", (25, 25), (18, 15), True, "training task 4, bottom-right room"),
        # Transfer tasks cross the centre opening; the paper runs them sparse.
        _task("room1to2", (11, 8), (14, 9), False, "transfer task, room 1 to room 2"),
        _task("room1to3", (8, 11), (9, 14), False, "transfer task, room 1 to room 3"),
        _task("room3to4", (11, 18), (14, 17), False, "transfer task, room 3 to room 4"),
    )
}

GRID_SEQUENCES: dict[str, tuple[str, ...]] = {
    "fourrooms": ("room1", "room2", "room3", "room4"),
}


def get_grid_task(name: str, dense: bool | None = None) -> GridTask:
    """Look up a task by name.

    Args:
        name: A key of :data:`GRID_TASKS`.
        dense: If not None, overrides the task's default reward type.

    Returns:
        The task, possibly with its reward type replaced.

    Raises:
        ValueError: If ``name`` is not a known task.
    """
    try:
        task = GRID_TASKS[name]
    except KeyError:
        valid = ", ".join(GRID_TASKS)
        raise ValueError(f"unknown task {name!r}; valid grid tasks: {valid}") from None
    if dense is not None and dense != task.dense:
        task = replace(task, dense=dense)
    return task
