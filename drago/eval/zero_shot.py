"""Zero-shot transfer that measures the world model: plan with the retained model and the task's true reward.

Nothing is learned and no learned head is used: the reward, policy and value heads stay out. On the grid
the reward of every task is known (:func:`true_reward` reproduces the env's, dense and sparse, as a batched
torch function of ``(obs, action, next_obs)``), so the only learned part in the loop is the world model.
Played for the model after each stage on every training room and the paper's transfer tasks, this gives a
zero-shot return matrix ``R[stage, task]`` (:func:`zero_shot_matrix`), whose GEM and Continual World
metrics say how much of the world the model kept in a usable form (:func:`matrix_metrics`).

The planner (:class:`LatticePlanner`) is finite-horizon dynamic programming over the model's one-step
predictions, replanned at every step (model-predictive control with an exhaustive lookahead):

* the model predicts the next observation of every lattice state (27 x 27 cells x 4 headings, walls
  included) under each of the 3 actions, once per model: one forward pass of 8,748 rows, the prediction
  exactly as the agent's planner sees it, ``WorldModel.forward(encode(obs), action)``;
* each prediction is decoded to the nearest state with the grid's own decoding (a non-finite one to an
  absorbing "lost" state that pays nothing), which turns the model into a deterministic transition table;
* with the true reward of each (state, action, predicted next state), backward induction over that table
  gives the best ``h``-step return of each action; at every step of a real episode the planner plays the
  best first action with ``h = min(horizon, steps left)``, ties broken uniformly on a seeded generator.

Why this planner rather than the agent's categorical CEM: the lookahead has to reach a goal in another
room (a transfer task's goal is 12 to 14 steps from its start, a training room's 18 to 22 from its corner),
the dense reward is gated to the goal's quadrant and a transfer's reward is sparse, so until a sampled
sequence reaches the goal every sequence scores 0 and CEM has nothing to refit. Exhaustive lookahead over
3 actions is exact instead, and on the lattice it costs a few table sweeps per step, so the horizon can be
the rest of the episode (the default, :data:`DEFAULT_HORIZON` = 100). With the true dynamics in place of
the model (:func:`ceiling`) the planner alone reaches the DP optimum of every task exactly; the default share
of random steps (:data:`DEFAULT_EPSILON`) costs 3-7% of it. ``benchmarks/zero_shot_ceiling.py`` measures
both, and how the ceiling falls with shorter horizons.

What the projection to the lattice means: errors smaller than half a cell never compound, as they would if
raw predictions were chained; a transition the model gets wrong by a cell or more (the exact-match errors
that :mod:`drago.eval.coverage` counts) is what the planner believes. The reward needs no projection of its
own: it is a function of decoded cells, like the env's. Nothing is learned during an episode either, so a
wrong transition on the way (a step through a block the model does not know) is believed at every step; the
random steps give the agent a chance to leave it, and the return is that of the model's own best plan
carried out in the real world.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import cache, lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch

from drago.config import Config
from drago.envs import GRID_DOMAIN, GRID_TASKS, exact_world, get_domain, make_env, task_optimum
from drago.envs.fourrooms import (
    EPISODE_LENGTH,
    SIZE,
    decode_observation,
)
from drago.envs.grid_reward import decode_obs, true_reward
from drago.envs.tasks import GRID_SEQUENCES, GridTask, get_grid_task
from drago.eval.coverage import grid_transitions, grid_world_models
from drago.eval.metrics import continual_metrics
from drago.seeding import task_seed
from drago.training.rundir import RunCheckpoint, RunDirError, write_rows_csv
from drago.training.rundir import run_checkpoints as _run_checkpoints

__all__ = [
    "CSV_COLUMNS",
    "DEFAULT_EPISODES",
    "DEFAULT_EPSILON",
    "DEFAULT_HORIZON",
    "GRID_TASKS_TRAINING",
    "LOST",
    "N_STATES",
    "READINGS",
    "ZERO_SHOT_FILE",
    "LatticeModel",
    "LatticePlanner",
    "ZeroShotError",
    "ceiling",
    "decode_obs",
    "default_tasks",
    "format_table",
    "is_paper_case",
    "lattice_model",
    "lattice_observations",
    "matrix_metrics",
    "model_dynamics",
    "play",
    "return_matrix",
    "run_checkpoints",
    "state_index",
    "true_dynamics",
    "true_reward",
    "write_zero_shot_csv",
    "zero_shot_matrix",
]

#: Lattice states: every (x, y, heading) of the 27 x 27 map, walls and blocks included (a model may
#: predict one), indexed by :func:`state_index`; then one absorbing state for non-finite predictions.
N_LATTICE = SIZE * SIZE * 4
LOST = N_LATTICE
N_STATES = N_LATTICE + 1
N_ACTIONS = 3
#: The planner's default lookahead: the whole episode, so every goal on the map is in sight.
DEFAULT_HORIZON = EPISODE_LENGTH
#: Episodes per (stage, task, reward); episode e starts facing heading e mod 4 (see :func:`play`).
DEFAULT_EPISODES = 4
#: Share of steps played with a uniformly random action instead of the plan. A planner that believes one
#: wrong transition on its route (a step through a block the model thinks open) replays it from the same
#: state forever and earns nothing for the rest of the episode, however good the model is elsewhere; a few
#: random steps let it leave, so one wrong transition costs a few steps rather than the episode. This is the
#: reason Atari agents are evaluated with epsilon = 0.05 (Mnih et al. 2015). 0 gives the deterministic form.
DEFAULT_EPSILON = 0.05
#: Which reward a task is read with: its catalogue's own (training rooms dense, transfers sparse), or either.
READINGS = ("task", "dense", "sparse")
CSV_COLUMNS: tuple[str, ...] = ("run", "method", "seed", "stage", "stage_task", "task", "reward", "return",
                                "return_std", "optimum", "fraction", "episodes", "horizon", "epsilon")
#: A suggested file name for a run's matrix (nothing here writes it into a run).
ZERO_SHOT_FILE = "zero_shot.csv"
#: The grid's training rooms, in the order of its sequence.
GRID_TASKS_TRAINING: tuple[str, ...] = GRID_SEQUENCES["fourrooms"]
# Two first actions are equally good when their lookahead returns differ by less than this: returns are
# sums of at most 100 rewards of at most 3, added in different orders along different paths.
TIE_TOLERANCE = 1e-9
# task_seed purpose of the tie-breaking stream, so it never coincides with a training stream.
_TIE_PURPOSE = 11
# The ceiling's stage number in seeds and rows: no model.
_CEILING_STAGE = 0

Dynamics = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class ZeroShotError(RunDirError):
    """A run or a request zero-shot planning cannot serve; the message is one line (the CLI prints it)."""


# ---- decoding (decode_obs and true_reward live with the grid: drago.envs.grid_reward) ---------------
def state_index(decoded: torch.Tensor) -> torch.Tensor:
    """(N, 3) decoded ``(x, y, dir)`` -> (N,) lattice index ``(x * 27 + y) * 4 + dir``; -1 rows -> :data:`LOST`."""
    index = (decoded[:, 0] * SIZE + decoded[:, 1]) * 4 + decoded[:, 2]
    return torch.where((decoded < 0).any(dim=1), torch.full_like(index, LOST), index)


# ---- dynamics ------------------------------------------------------------------------------------------
@lru_cache(maxsize=1)
def _lattice() -> tuple[np.ndarray, np.ndarray]:
    """The observation of every lattice state, and the true next observation of each (state, action)."""
    x, y, d = np.meshgrid(np.arange(SIZE), np.arange(SIZE), np.arange(4), indexing="ij")
    x, y, d = x.ravel(), y.ravel(), d.ravel()
    # observation()'s arithmetic: float64, then float32.
    obs = np.stack([2.0 * x / SIZE - 1.0, 2.0 * y / SIZE - 1.0, 2.0 * d / 4.0 - 1.0], axis=1).astype(np.float32)
    # A state the agent cannot be in (a wall or a block) stays where it is; the true dynamics never lead there.
    following = np.repeat(obs[:, None, :], N_ACTIONS, axis=1)
    data = grid_transitions()
    rows = (data.cells[:, 0] * SIZE + data.cells[:, 1]) * 4 + data.headings
    following[rows, data.action_idx] = data.next_obs
    for array in (obs, following):
        array.setflags(write=False)
    return obs, following


def lattice_observations() -> np.ndarray:
    """(2916, 3) float32: the observation of every lattice state, in :func:`state_index` order."""
    return _lattice()[0]


def true_dynamics(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """The true next observation, from the grid's transition table (:func:`~drago.eval.coverage.grid_transitions`).

    Args:
        obs: (N, 3) observations (decoded to the nearest state first).
        action: (N, 3) one-hot actions (the argmax is taken, as the env does).

    Returns:
        (N, 3) float32 next observations; a non-finite observation is returned as it is.
    """
    table = torch.from_numpy(np.array(_lattice()[1])).to(obs.device)
    index = state_index(decode_obs(obs))
    lost = index == LOST
    out = table[index.clamp_max(N_LATTICE - 1), action.argmax(dim=1)]
    return torch.where(lost[:, None], obs.to(torch.float32), out)


def model_dynamics(world_model: torch.nn.Module) -> Dynamics:
    """The world model's prediction as its planner sees it: ``world_model(world_model.encode(obs), action)``."""
    def predict(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        with torch.inference_mode():
            return world_model(world_model.encode(obs), action).float()

    return predict


@dataclass(frozen=True)
class LatticeModel:
    """A dynamics function evaluated on every lattice state: a deterministic transition table.

    Attributes:
        obs: (2916, 3) float32 lattice observations.
        predicted: (2916, 3, 3) float32 predicted next observation per (state, action).
        successor: (2917, 3) int64 next state per (state, action); :data:`LOST` is absorbing.
    """

    obs: np.ndarray
    predicted: np.ndarray
    successor: np.ndarray

    def rewards(self, task: GridTask) -> np.ndarray:
        """(2917, 3) float64 true reward of each (state, action) under this table; 0 from :data:`LOST`."""
        obs = torch.from_numpy(np.repeat(self.obs, N_ACTIONS, axis=0))
        action = torch.eye(N_ACTIONS).repeat(N_LATTICE, 1)
        following = torch.from_numpy(self.predicted.reshape(-1, 3))
        reward = np.zeros((N_STATES, N_ACTIONS))
        reward[:N_LATTICE] = true_reward(task, obs, action, following).numpy().reshape(N_LATTICE, N_ACTIONS)
        return reward


def lattice_model(dynamics: Dynamics, device: str | torch.device = "cpu") -> LatticeModel:
    """Evaluate ``dynamics`` once on every (lattice state, action): 8,748 rows in one call."""
    obs = lattice_observations()
    batch = torch.from_numpy(np.repeat(obs, N_ACTIONS, axis=0)).to(device)
    actions = torch.eye(N_ACTIONS, device=device).repeat(N_LATTICE, 1)
    predicted = dynamics(batch, actions).detach().float()
    if predicted.shape != batch.shape:
        raise ValueError(f"dynamics returned shape {tuple(predicted.shape)}, expected {tuple(batch.shape)}")
    successor = np.full((N_STATES, N_ACTIONS), LOST, dtype=np.int64)
    successor[:N_LATTICE] = state_index(decode_obs(predicted)).cpu().numpy().reshape(N_LATTICE, N_ACTIONS)
    predicted_np = predicted.cpu().numpy().reshape(N_LATTICE, N_ACTIONS, 3)
    return LatticeModel(obs=obs, predicted=predicted_np, successor=successor)


# ---- the planner ---------------------------------------------------------------------------------------
class LatticePlanner:
    """Receding-horizon dynamic programming with the true reward over a :class:`LatticeModel`.

    ``values[k]`` is the best k-step return from each state under the model (``values[0] = 0``); the
    planner's action values with ``h`` steps to look ahead are ``reward + values[h - 1][successor]``.
    """

    def __init__(self, model: LatticeModel, task: GridTask, horizon: int = DEFAULT_HORIZON):
        if int(horizon) < 1:
            raise ValueError(f"horizon must be at least 1, got {horizon}")
        self.horizon = int(horizon)
        self.successor = model.successor
        self.reward = model.rewards(task)
        values = np.zeros((self.horizon, N_STATES))
        for k in range(1, self.horizon):
            values[k] = (self.reward + values[k - 1][self.successor]).max(axis=1)
        self.values = values

    def action_values(self, state: int, steps_left: int) -> np.ndarray:
        """(3,) lookahead return of each first action from ``state`` with ``min(horizon, steps_left)`` steps."""
        h = max(1, min(self.horizon, int(steps_left)))
        return self.reward[state] + self.values[h - 1][self.successor[state]]

    def tie_tolerance(self, top: float) -> float:
        """How close to the best an action's value must be to count as equally good."""
        return TIE_TOLERANCE

    def act(self, state: int, steps_left: int, generator: torch.Generator) -> int:
        """The best first action from ``state``; among equally good ones, one drawn from ``generator``."""
        q = self.action_values(state, steps_left).tolist()
        top = max(q)
        best = [a for a, value in enumerate(q) if value >= top - self.tie_tolerance(top)]
        if len(best) == 1:
            return best[0]
        return best[int(torch.randint(len(best), (1,), generator=generator))]


def play(model: LatticeModel, task: GridTask, episodes: int = DEFAULT_EPISODES, seed: int = 0, stage: int = 0,
         horizon: int = DEFAULT_HORIZON, epsilon: float = DEFAULT_EPSILON, planner: Any = None) -> np.ndarray:
    """Play ``episodes`` episodes of ``task`` in the real env, planning over ``model``.

    Episode e starts on the task's start cell facing heading e mod 4: the env draws the heading uniformly,
    and cycling makes every 4 episodes an exact average over it, the average the DP optimum takes. Its
    random steps (``epsilon``, see :data:`DEFAULT_EPSILON`) and its ties are drawn from a generator of its
    own, seeded from (seed, stage, task, reward type, e), so an episode does not depend on how many others
    are played; torch's global generator is never used. With ``epsilon`` 0 nothing is drawn but ties.

    ``planner`` replaces the true-reward :class:`LatticePlanner` with another that has its ``act`` (planning
    with learned heads, :class:`drago.eval.components.HeadsPlanner`); ``horizon`` is then unused.

    Returns:
        (episodes,) float64 undiscounted returns.
    """
    planner = planner if planner is not None else LatticePlanner(model, task, horizon)
    env = make_env(GRID_DOMAIN, task.name, dense_reward=task.dense)
    task_number = list(GRID_TASKS).index(task.name)
    returns = np.zeros(int(episodes))
    try:
        for e in range(int(episodes)):
            episode_seed = task_seed(int(seed), int(stage), _TIE_PURPOSE, task_number, int(task.dense), e)
            generator = torch.Generator().manual_seed(episode_seed)
            env.reset(seed=episode_seed)
            obs = env.unwrapped.set_state(task.start, e % 4)
            for t in range(EPISODE_LENGTH):
                x, y, d = decode_observation(obs)
                state = (x * SIZE + y) * 4 + d
                if epsilon > 0 and float(torch.rand((), generator=generator)) < epsilon:
                    action = int(torch.randint(N_ACTIONS, (), generator=generator))
                else:
                    action = planner.act(state, EPISODE_LENGTH - t, generator)
                obs, reward, terminated, truncated, _ = env.step(action)
                returns[e] += reward
                if terminated or truncated:
                    break
    finally:
        env.close()
    return returns


# ---- tasks and rows ------------------------------------------------------------------------------------
def default_tasks(training_tasks: Sequence[str]) -> list[str]:
    """A run's training rooms, then the paper's transfer tasks on the grid, each once."""
    return list(dict.fromkeys([*training_tasks, *(task for task, _ in get_domain(GRID_DOMAIN).transfer_cases)]))


def _resolve(tasks: Iterable[str], readings: Iterable[str]) -> list[GridTask]:
    tasks, readings = list(tasks), list(readings)
    unknown = [t for t in tasks if t not in GRID_TASKS]
    if unknown:
        raise ZeroShotError(f"unknown grid task(s) {', '.join(unknown)}; valid tasks: {', '.join(GRID_TASKS)}")
    bad = [r for r in readings if r not in READINGS]
    if bad or not readings:
        raise ZeroShotError(f"reward readings must be among {', '.join(READINGS)}; got {', '.join(bad) or 'none'}")
    if not tasks:
        raise ZeroShotError("no task to evaluate")
    out: dict[tuple[str, bool], GridTask] = {}
    for name in tasks:
        for reading in readings:
            task = get_grid_task(name, dense=None if reading == "task" else reading == "dense")
            out.setdefault((name, task.dense), task)
    return list(out.values())


@cache
def _optimum(name: str, dense: bool) -> float:
    value = task_optimum(GRID_DOMAIN, name, dense)
    assert value is not None
    return float(value)


def _row(task: GridTask, returns: np.ndarray, horizon: int, epsilon: float, **head: Any) -> dict[str, Any]:
    optimum = _optimum(task.name, task.dense)
    mean = float(np.mean(returns))
    return {**head, "task": task.name, "reward": "dense" if task.dense else "sparse", "return": mean,
            # Population std over the episodes, as eval.csv's episode_reward_std.
            "return_std": float(np.std(returns)), "optimum": optimum, "fraction": mean / optimum,
            "episodes": len(returns), "horizon": int(horizon), "epsilon": float(epsilon)}


def _check_budget(episodes: int, horizon: int, epsilon: float) -> None:
    if int(episodes) < 1:
        raise ZeroShotError(f"episodes must be at least 1, got {episodes}")
    if int(horizon) < 1:
        raise ZeroShotError(f"horizon must be at least 1, got {horizon}")
    if not 0 <= float(epsilon) < 1:
        raise ZeroShotError(f"epsilon must be in [0, 1), got {epsilon}")


def run_checkpoints(run_dir: str | Path) -> tuple[Config, list[RunCheckpoint]]:
    """The run's config and finished stages' checkpoints; refuses a run whose domain is not the grid.

    Raises:
        ZeroShotError: not a run directory, not a grid run, or no task finished yet (one line).
        drago.config.ConfigError: the run's ``config.yaml`` is invalid.
    """
    try:
        return _run_checkpoints(run_dir, ZeroShotError, lambda cfg: (
            f"zero-shot planning needs a tabular domain with a known reward: the grid only (domains on an exact "
            f"world); {cfg.env.domain} is not one" if exact_world(cfg.env.domain) is None else None))
    except ZeroShotError:
        raise
    except RunDirError as err:  # the run directory's own reader (no such folder, no config.yaml)
        raise ZeroShotError(str(err)) from None


def zero_shot_matrix(run_dir: str | Path, tasks: Sequence[str] | None = None, episodes: int = DEFAULT_EPISODES,
                     seed: int = 0, device: str = "cpu", readings: Sequence[str] = ("task",),
                     horizon: int = DEFAULT_HORIZON, epsilon: float = DEFAULT_EPSILON) -> list[dict[str, Any]]:
    """The zero-shot return matrix of a grid run: plan with the world model after each finished stage.

    Args:
        run_dir: a run directory of the grid.
        tasks: task names; default the run's training rooms, then the paper's transfer tasks.
        episodes: episodes per (stage, task, reward); episode e starts facing heading e mod 4.
        seed: seeds the planner's tie-breaking (and the env resets) per (stage, task, reward, episode).
        device: torch device of the world model (one forward pass per stage).
        readings: which rewards: ``"task"`` the task's own (training rooms dense, transfers sparse),
            ``"dense"``, ``"sparse"``; a task read twice the same way appears once.
        horizon: the planner's lookahead (capped by the steps left in the episode).
        epsilon: share of steps played with a random action (:data:`DEFAULT_EPSILON`).

    Returns:
        Rows with the keys of :data:`CSV_COLUMNS`, one per (stage, task, reward), stages in order. ``seed``
        is the run's training seed, ``stage`` the task index + 1 after which the model was saved,
        ``stage_task`` that task, ``return`` the mean over episodes and ``return_std`` its population
        std, ``fraction`` the return over the task's DP optimum.

    Raises:
        ZeroShotError: a run that is not a grid run, has no finished stage, or a bad argument (one line).
        drago.training.checkpoint.CheckpointError: a corrupt or mismatched checkpoint.
    """
    _check_budget(episodes, horizon, epsilon)
    cfg, checkpoints = run_checkpoints(run_dir)
    resolved = _resolve(default_tasks(cfg.env.tasks) if tasks is None else tasks, readings)
    rows: list[dict[str, Any]] = []
    refusal = "zero-shot planning needs a tabular domain with a known reward: the grid only (domains on an exact world)"
    for checkpoint, predictor in grid_world_models(checkpoints, device, refusal, ZeroShotError):
        model = lattice_model(model_dynamics(predictor.world_model), device=device)
        for task in resolved:
            returns = play(model, task, episodes, seed, checkpoint.stage, horizon, epsilon)
            rows.append(_row(task, returns, horizon, epsilon, run=str(run_dir), method=cfg.method.name,
                             seed=cfg.train.seed, stage=checkpoint.stage, stage_task=checkpoint.task))
    return rows


def ceiling(tasks: Sequence[str] | None = None, episodes: int = DEFAULT_EPISODES, seed: int = 0,
            readings: Sequence[str] = ("dense", "sparse"), horizon: int = DEFAULT_HORIZON,
            epsilon: float = DEFAULT_EPSILON) -> list[dict[str, Any]]:
    """The evaluation's ceiling: :func:`zero_shot_matrix`'s planning with the true dynamics in place of a model.

    Rows have the same keys, with ``run`` = ``"ceiling"``, ``method`` = ``"true-dynamics"``, ``seed`` the
    evaluation seed and ``stage`` 0. Default tasks: the four training rooms and the transfer tasks, each
    read dense and sparse.
    """
    _check_budget(episodes, horizon, epsilon)
    resolved = _resolve(default_tasks(GRID_TASKS_TRAINING) if tasks is None else tasks, readings)
    model = lattice_model(true_dynamics)
    return [_row(task, play(model, task, episodes, seed, _CEILING_STAGE, horizon, epsilon), horizon, epsilon,
                 run="ceiling", method="true-dynamics", seed=int(seed), stage=_CEILING_STAGE, stage_task="")
            for task in resolved]


def write_zero_shot_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """Write zero-shot rows (columns :data:`CSV_COLUMNS`) to ``path``, replacing it atomically."""
    return write_rows_csv(rows, CSV_COLUMNS, path)


# ---- reading the matrix --------------------------------------------------------------------------------
def is_paper_case(row: dict[str, Any]) -> bool:
    """Whether a row is one of the paper's transfer cases (room1to2 after 2, room1to3 after 3 and 4,
    room3to4 after 4), at any reward reading."""
    return (row["task"], int(row["stage"])) in get_domain(GRID_DOMAIN).transfer_cases


def return_matrix(rows: list[dict[str, Any]], reward: str | None = None,
                  value: str = "fraction") -> tuple[list[int], list[str], np.ndarray]:
    """One run's rows as a matrix ``R[stage, task]``.

    Args:
        rows: rows of :func:`zero_shot_matrix` for one run.
        reward: ``"dense"`` or ``"sparse"`` to keep one reading; None keeps each task's first reading.
        value: the row key to fill ``R`` with, ``"fraction"`` or ``"return"``.

    Returns:
        (stages, tasks, R) with R of shape (len(stages), len(tasks)), NaN where a cell has no row; tasks in
        the order they first appear (training rooms first in :func:`zero_shot_matrix`'s rows).

    Raises:
        ValueError: rows of more than one run.
    """
    runs = {row["run"] for row in rows}
    if len(runs) > 1:
        raise ValueError(f"return_matrix takes the rows of one run; got {len(runs)} runs")
    kept: dict[tuple[int, str], float] = {}
    for row in rows:
        if reward is None or row["reward"] == reward:
            kept.setdefault((int(row["stage"]), row["task"]), float(row[value]))
    stages = sorted({stage for stage, _ in kept})
    tasks = list(dict.fromkeys(task for _, task in kept))
    R = np.full((len(stages), len(tasks)), math.nan)
    for (stage, task), v in kept.items():
        R[stages.index(stage), tasks.index(task)] = v
    return stages, tasks, R


def matrix_metrics(rows: list[dict[str, Any]], training_tasks: Sequence[str] = GRID_TASKS_TRAINING,
                   value: str = "fraction") -> list[dict[str, Any]]:
    """GEM and Continual World metrics (:func:`~drago.eval.metrics.continual_metrics`) of each run's matrix.

    The metrics speak of the training rooms: ``R[i, j]`` is the zero-shot ``value`` on training room j
    after stage i, over the stages the run finished. One result per (run, reward reading).

    Returns:
        Dicts with run, method, seed, reward, stages and the keys of ``continual_metrics`` (acc, bwt,
        average_performance, forgetting).
    """
    out: list[dict[str, Any]] = []
    for run in dict.fromkeys(row["run"] for row in rows):
        mine = [row for row in rows if row["run"] == run and row["task"] in training_tasks]
        for reward in dict.fromkeys(row["reward"] for row in mine):
            stages, tasks, R = return_matrix(mine, reward, value)
            order = [t for t in training_tasks if t in tasks]
            R = R[:, [tasks.index(t) for t in order]]
            if not len(stages) or R.shape[1] < len(stages) or not np.isfinite(R[:, :len(stages)]).all():
                continue
            first = mine[0]
            out.append({"run": run, "method": first["method"], "seed": first["seed"], "reward": reward,
                        "stages": len(stages), **continual_metrics(R)})
    return out


def format_table(rows: list[dict[str, Any]], value: str = "fraction") -> list[str]:
    """Compact text table: one line per (run, stage) with ``value`` per task; ``*`` marks a paper case.

    A task read both ways has two columns, ``task:d`` (dense) and ``task:s`` (sparse).
    """
    columns = list(dict.fromkeys((row["task"], row["reward"]) for row in rows))
    twice = {task for task, _ in columns if sum(t == task for t, _ in columns) > 1}
    labels = [f"{task}:{reward[0]}" if task in twice else task for task, reward in columns]
    lines: dict[tuple[str, int], dict[Any, Any]] = {}
    for row in rows:
        entry = lines.setdefault((row["run"], int(row["stage"])), {"after": row["stage_task"]})
        entry[(row["task"], row["reward"])] = f"{row[value]:.3f}" + ("*" if is_paper_case(row) else " ")
    width = max([len("run")] + [len(run) for run, _ in lines])
    col = max([7] + [len(label) + 1 for label in labels])
    out = [f"{'run':<{width}}  stage  {'after':<8}" + "".join(f"  {label:>{col}} " for label in labels)]
    for (run, stage), entry in lines.items():
        cells = "".join(f"  {entry.get(key, '-'):>{col + 1}}" for key in columns)
        out.append(f"{run:<{width}}  {stage:>5}  {entry['after'] or '-':<8}{cells}")
    return out
