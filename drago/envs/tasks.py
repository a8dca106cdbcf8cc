"""Task catalogues: the four-rooms MiniGrid world (paper Appendix C) and DeepMind Control (paper Appendix C).

Tasks are plain data. A grid task is a start cell, a goal cell and the reward type; the world itself
lives in :mod:`drago.envs.fourrooms`. A DeepMind Control task names a reward family and its parameters;
the physics and the reward formulas live in :mod:`drago.envs.dmc`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

__all__ = ["GridTask", "GRID_TASKS", "GRID_SEQUENCES", "get_grid_task", "DmcTask", "DMC_TASKS", "DMC_SEQUENCES",
           "DMC_REWARD_KINDS", "DmcTransferTask", "DMC_TRANSFER_TASKS", "get_dmc_task"]


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


# ---------------------------------------------------------------------------------------------------
# DeepMind Control: cheetah and walker (paper Appendix C)
# ---------------------------------------------------------------------------------------------------

#: Reward kinds of :class:`DmcTask`; the formulas live in :mod:`drago.envs.dmc`.
DMC_REWARD_KINDS = ("cheetah-run", "cheetah-jump", "cheetah-jump-and-run", "walker")


@dataclass(frozen=True)
class DmcTask:
    """One DeepMind Control task: a domain's stock physics with one reward (paper Appendix C).

    Every task of a domain shares the stock XML and the stock initial-state distribution; the custom
    XMLs of the official code differ from stock only visually (docs: Environments, DeepMind Control).

    Attributes:
        name: Task id as in the official configs, e.g. ``"cheetah-run-backwards"``.
        domain: ``"cheetah"`` or ``"walker"``.
        kind: Which reward family (see :data:`DMC_REWARD_KINDS`).
        speed: Target speed S in m/s (0: none; walker-stand).
        direction: +1 forward, -1 backward (0 where the reward has no direction).
        stock: True for a task of the stock dm_control suite, False for a custom one (TD-MPC2 / DRAGO).
        description: One line shown by ``drago list``.
    """

    name: str
    domain: str
    kind: str
    speed: float
    direction: int
    stock: bool
    description: str

    @property
    def reward(self) -> str:
        """The per-control-step reward as a short closed form (paper Appendix C)."""
        s = f"{self.speed:g}"
        sign = "" if self.direction >= 0 else "-"
        if self.kind == "cheetah-run":
            return f"clip({sign}vx/{s}, 0, 1)"
        if self.kind == "cheetah-jump":
            return ("mean over feet f of (5 tol((z_torso+z_f)/2; [1.2,inf), m=0.6) "
                    "+ tol(vx; [-0.5,0.5], m=0.5, linear)) / 6")
        if self.kind == "cheetah-jump-and-run":
            return f"(mean over feet f of tol((z_torso+z_f)/2; [0.9,inf), m=0.45) + clip({sign}vx/{s}, 0, 1)) / 2"
        stand = "(3 tol(z_torso; [1.2,inf), m=0.6) + (1+up)/2) / 4"
        if self.speed == 0:
            return f"stand = {stand}"
        return f"stand * (5 clip({sign}vx/{s}, 0, 1) + 1) / 6, stand = {stand}"


def _dmc(name: str, kind: str, speed: float, direction: int, stock: bool, what: str) -> DmcTask:
    return DmcTask(name, name.split("-", 1)[0], kind, speed, direction, stock, what)


DMC_TASKS: dict[str, DmcTask] = {
    t.name: t
    for t in (
        _dmc("cheetah-run", "cheetah-run", 10, 1, True, "training task 1; transfer target"),
        _dmc("cheetah-jump", "cheetah-jump", 0.5, 0, False, "training task 2: stand tall on each foot in turn"),
        _dmc("cheetah-run-backwards", "cheetah-run", 8, -1, False, "training task 3; transfer target"),
        _dmc("cheetah-jump-and-run", "cheetah-jump-and-run", 7.5, 1, False, "test task jump&run"),
        _dmc("cheetah-jump-and-run-backwards", "cheetah-jump-and-run", 7.5, -1, False, "test task jump&back"),
        _dmc("walker-stand", "walker", 0, 0, True, "training task 4"),
        _dmc("walker-walk", "walker", 1, 1, True, "training task 2"),
        _dmc("walker-run", "walker", 8, 1, True, "training task 1; transfer target"),
        _dmc("walker-walk-backwards", "walker", 1, -1, False, "training task 3"),
        _dmc("walker-run-backwards", "walker", 8, -1, False, "transfer target of run2back"),
    )
}

#: The continual sequences of the official configs (paper Appendix C; the config's walker order is authoritative).
DMC_SEQUENCES: dict[str, tuple[str, ...]] = {
    "cheetah": ("cheetah-run", "cheetah-jump", "cheetah-run-backwards"),
    "walker": ("walker-run", "walker-walk", "walker-walk-backwards", "walker-stand"),
}


@dataclass(frozen=True)
class DmcTransferTask:
    """One test task of the paper's Table 1 (paper §4.4, Table 1). Data only: the runner lives elsewhere.

    Attributes:
        name: Short id, e.g. ``"jump2run"`` (the paper's "jump&run" is ``"jump-and-run"``).
        domain: ``"cheetah"`` or ``"walker"``.
        target: The task learned in the test (a key of :data:`DMC_TASKS`).
        pre_rollout_source: The training task whose learner policy (that task's checkpoint, eval-mode
            planner) runs ``pre_rollout_steps`` agent steps after each reset of learner and evaluation
            episodes before the test episode starts; None: episodes start from a plain reset.
        after: The training task after which the world model is taken (its stage in the sequence is
            :attr:`stage`).
        after_inferred: True where the paper does not say which stage and drago infers it from the sequence.
        pre_rollout_steps: Agent steps of the pre-rollout (the code's ``pre_rollout_steps=100``).
        paper_name: The name in the paper's table.
    """

    name: str
    domain: str
    target: str
    pre_rollout_source: str | None
    after: str
    after_inferred: bool
    paper_name: str
    pre_rollout_steps: int = 100

    @property
    def stage(self) -> int:
        """1-based position of :attr:`after` in the domain's sequence (the ``--after`` of a transfer)."""
        return DMC_SEQUENCES[self.domain].index(self.after) + 1

    @property
    def pre_rollout_stage(self) -> int | None:
        """1-based stage whose checkpoint holds the pre-rollout policy, or None."""
        if self.pre_rollout_source is None:
            return None
        return DMC_SEQUENCES[self.domain].index(self.pre_rollout_source) + 1


DMC_TRANSFER_TASKS: dict[str, DmcTransferTask] = {
    t.name: t
    for t in (
        DmcTransferTask("jump2run", "cheetah", "cheetah-run", "cheetah-jump", "cheetah-jump", False,
                        "Cheetah jump2run"),
        DmcTransferTask("jump2back", "cheetah", "cheetah-run-backwards", "cheetah-jump", "cheetah-run-backwards",
                        True, "Cheetah jump2back"),
        DmcTransferTask("jump-and-run", "cheetah", "cheetah-jump-and-run", None, "cheetah-jump", False,
                        "Cheetah jump&run"),
        DmcTransferTask("jump-and-back", "cheetah", "cheetah-jump-and-run-backwards", None, "cheetah-run-backwards",
                        True, "Cheetah jump&back"),
        DmcTransferTask("walk2run", "walker", "walker-run", "walker-walk", "walker-walk", True, "Walker walk2run"),
        DmcTransferTask("run2back", "walker", "walker-run-backwards", "walker-run", "walker-walk-backwards", True,
                        "Walker run2back"),
        DmcTransferTask("back2run", "walker", "walker-run", "walker-walk-backwards", "walker-walk-backwards", True,
                        "Walker back2run"),
        DmcTransferTask("stand2run", "walker", "walker-run", "walker-stand", "walker-stand", True,
                        "Walker stand2run"),
    )
}


def get_dmc_task(name: str) -> DmcTask:
    """Look up a DeepMind Control task by name; ValueError names the valid ones."""
    try:
        return DMC_TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; valid DeepMind Control tasks: {', '.join(DMC_TASKS)}") from None
