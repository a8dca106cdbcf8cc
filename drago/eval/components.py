"""Which part forgot: per-component retention of a TD-MPC agent on the grid, and the swap test.

A model-based agent has parts that can forget separately: the world model's dynamics, and each task's heads
(reward, twin Q, policy) that the planner combines with it. The paper's claim is about the world model
(paper §3), so this module measures each part on a **frozen probe set** per task, the same for every method
and seed (docs: Evaluation, "Which part forgot"):

* the probe of a grid task is every (state, action) of its room: 4 headings x 3 actions on each of the room's
  cells, with the true next state, the task's true reward, and the discounted DP optimum ``Q*`` of the task
  under the agent's discount (value iteration over the grid's exact transition table);
* after each stage N, for every task k seen so far, with the model after N and the heads saved after k:

  - ``dynamics_1step``: share of probe transitions the model predicts exactly (decoded to the lattice; the
    coverage of task k's room);
  - ``dynamics_hstep``: share of probe states from which an open-loop rollout of the model along the optimal
    actions for H steps (the agent's planning horizon) ends on the true state;
  - ``reward_error``: mean absolute error of the reward head against the task's true reward;
  - ``value_error``: mean absolute error of min(Q1, Q2) against ``Q*``, divided by the mean ``|Q*|`` of the
    probe (so 0 is exact and 1 is as large as the values themselves);
  - ``value_order``: rank correlation of min(Q1, Q2) with ``Q*`` over the probe (1: the critic orders the
    probe's state-actions as the optimum does, whatever its scale; 0: no order). A critic far from ``Q*``'s
    scale can still steer a planner that adds it at the horizon, so the order is read beside the error;
  - ``policy_agreement``: share of probe states where the policy head's action is an optimal one;
  - ``return_own_heads``: the return on task k of planning with the model and task k's heads (below), as a
    fraction of the task's DP optimum. Planning with the model and the *true* reward is the zero-shot matrix
    (:mod:`drago.eval.zero_shot`), which a unit records beside this.

**Planning with heads** is exact dynamic programming over the model's lattice table, as the zero-shot planner
does, with the learned reward in place of the true one and the learned value at the horizon: the best
H-step return ``sum_t gamma^t r_hat + gamma^H V_hat(s_H)`` of each first action, replanned every step. It is
what TD-MPC's planner approximates with sampling (paper §2), without the sampling noise, so two heads compare
on the same footing as two models do in the zero-shot matrix.

**The swap test** for an earlier task k after stage N (forgetting attribution, as representation-forgetting
probes do in supervised continual learning): the return on task k of (a) the model and heads saved after k,
(b) the model after N under the heads saved after k, (c) the model after N with the heads of k refit on task
k's probe, and (d) the model after N with the true reward (the zero-shot matrix). a -> b is the whole loss,
b -> c what a cheap head refit recovers (that knowledge was still in the model), and what c leaves is the
model's own forgetting.

**The refit** re-attaches the heads saved after k and trains them with the agent's own update (paper §2's
losses and optimizers) for a tenth of a task's learner steps in updates, at most :data:`REFIT_UPDATES` (on
``minigrid-cpu`` about a tenth of the updates one task trains its heads with), of H-step sequences that start
on probe states and follow uniformly random actions through the true dynamics, paid the task's true reward: a
fixed budget, the same for every method of a preset, and short beside what the heads were trained with. Its
learning rate decays linearly from the agent's to :data:`REFIT_LR_DECAY` of it over those updates, so that it
reads where heads trained through the model settle rather than where a short refit at a constant learning rate
happens to stop. It settles in more cases than the short refit, not in all (``benchmarks/refit_budget.py``
compares budgets; docs: Evaluation, "Which part forgot"). It cannot teach the model anything: the update runs
with ``train_world_model=False``, so the world model's optimizer never steps, the heads see the model's latents
detached, and the model's weights are checked unchanged afterwards. A refit's return can still be close to
all or nothing (its planner reaches the goal or does not), so the swap test makes :data:`REFIT_DRAWS` refits
with their own seeds and records their mean return, with the lowest and highest.

PETS has no value or policy heads and a reward head of its own kind: for a PETS run only the dynamics rows
are measured, and the others say so.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch

from drago.agent.agent import Agent
from drago.agent.buffer import Batch
from drago.agent.networks import TaskHeads
from drago.agent.protocol import capabilities_of
from drago.agent.speed import with_speed
from drago.config import AgentConfig
from drago.envs.tasks import GridTask, get_grid_task
from drago.envs import GRID_DOMAIN, exact_world
from drago.eval.coverage import grid_transitions, task_room, transition_groups
from drago.eval.zero_shot import (
    N_ACTIONS,
    N_LATTICE,
    N_STATES,
    TIE_TOLERANCE,
    Dynamics,
    LatticeModel,
    LatticePlanner,
    decode_obs,
    lattice_model,
    lattice_observations,
    model_dynamics,
    play,
    state_index,
    true_dynamics,
)
from drago.training.rundir import RunDirError, write_rows_csv
from drago.training.rundir import run_checkpoints as _run_checkpoints

__all__ = ["COMPONENTS", "COMPONENTS_FILE", "REFIT_DRAWS", "REFIT_LR_DECAY", "REFIT_UPDATES", "SWAP_FILE",
           "ComponentsError", "GridProbe", "HeadsPlanner", "RunStages", "component_errors", "components_checkpoints",
           "components_of_run", "evaluate_components", "grid_probe", "heads_return", "load_run_stages",
           "rank_correlation", "refit_heads", "write_components_csv", "write_swap_csv"]

COMPONENTS = ("dynamics_1step", "dynamics_hstep", "reward_error", "value_error", "value_order", "policy_agreement",
              "return_own_heads")
COMPONENTS_FILE = "components.csv"
SWAP_FILE = "swap.csv"
COMPONENT_COLUMNS = ("run", "method", "seed", "stage", "stage_task", "task", "component", "value", "note")
SWAP_COLUMNS = ("run", "method", "seed", "stage", "stage_task", "task", "optimum", "saved", "moved", "refit",
                "true_reward", "refit_updates", "refit_min", "refit_max", "refit_draws")
#: The most head updates of the swap test's refit; a run with shorter tasks gets a tenth of a task's learner steps
#: (see the module docstring).
REFIT_UPDATES = 1000
#: The refit's learning rate at its last update, as a fraction of the agent's (see the module docstring).
REFIT_LR_DECAY = 0.01
#: Independent refits of each swap-test case, whose mean return is its refit column (see the module docstring).
REFIT_DRAWS = 3
#: Rows of each refit update's batch.
REFIT_BATCH = 256
#: Episodes of each planning return (one per start heading, as the zero-shot matrix plays).
EPISODES = 4
# Value iteration stops when no Q* changes by more than this (gamma = 0.99 converges in about 2,500 sweeps).
_Q_TOLERANCE = 1e-9


class ComponentsError(RunDirError):
    """A run or request the component measures cannot serve; the message is one line."""


# ---- the probe -----------------------------------------------------------------------------------------
@lru_cache(maxsize=1)
def _true_lattice() -> LatticeModel:
    return lattice_model(true_dynamics)


def _task(name: str, dense: bool | None) -> GridTask:
    task = get_grid_task(name)
    return task if dense is None else dataclasses.replace(task, dense=bool(dense))


@lru_cache(maxsize=16)
def optimal_q(task_name: str, discount: float, dense: bool | None = None) -> np.ndarray:
    """(2917, 3) discounted optimal action values of a grid task under the true dynamics (value iteration);
    ``dense`` None reads the task with its own reward."""
    lattice = _true_lattice()
    reward = lattice.rewards(_task(task_name, dense))
    q = np.zeros((N_STATES, N_ACTIONS))
    for _ in range(100_000):
        updated = reward + discount * q[lattice.successor].max(axis=2)
        if np.abs(updated - q).max() <= _Q_TOLERANCE:
            q = updated
            break
        q = updated
    q.setflags(write=False)
    return q


@dataclass(frozen=True)
class GridProbe:
    """A task's frozen probe: every (state, action) of its room.

    Attributes:
        task: the grid task.
        obs, actions, next_obs: (n, 3) float32 observation, one-hot action and true next observation.
        reward: (n,) the task's true reward of each transition.
        q_star: (n,) the discounted DP optimum of each (state, action).
        optimal: (n,) whether the action is an optimal one at its state.
        states: (m,) lattice indices of the probe's states (every third row's state).
        discount: the discount ``q_star`` was computed with.
    """

    task: GridTask
    obs: np.ndarray
    actions: np.ndarray
    next_obs: np.ndarray
    reward: np.ndarray
    q_star: np.ndarray
    optimal: np.ndarray
    states: np.ndarray
    discount: float


@lru_cache(maxsize=16)
def grid_probe(task_name: str, discount: float, dense: bool | None = None) -> GridProbe:
    """The probe of a training room (start and goal in one room), the same for every run; ``dense`` None
    reads the task with its own reward (a run's ``env.dense_reward`` otherwise).

    Raises:
        ComponentsError: a task that does not live in one room (a transfer task).
    """
    room = task_room(task_name)
    if room is None:
        raise ComponentsError(f"{task_name} does not live in one room; probes are defined for the training rooms")
    data = grid_transitions()
    rows = np.flatnonzero(transition_groups() == room)
    obs, actions, next_obs = data.obs[rows], data.actions[rows], data.next_obs[rows]
    index = state_index(decode_obs(torch.from_numpy(obs))).numpy()
    task = _task(task_name, dense)
    q = optimal_q(task_name, float(discount), dense)
    q_rows = q[index, data.action_idx[rows]]
    best = q[index].max(axis=1)
    reward = _true_lattice().rewards(task)[index, data.action_idx[rows]]
    return GridProbe(task=task, obs=obs, actions=actions, next_obs=next_obs, reward=reward,
                     q_star=q_rows, optimal=q_rows >= best - 1e-6 * np.maximum(1.0, np.abs(best)),
                     states=index[::N_ACTIONS], discount=float(discount))


# ---- planning with heads -------------------------------------------------------------------------------
def _latents(model: torch.nn.Module, obs: np.ndarray | torch.Tensor) -> torch.Tensor:
    obs = obs.float() if isinstance(obs, torch.Tensor) else torch.from_numpy(np.array(obs, dtype=np.float32))
    with torch.inference_mode():
        return model.encode(obs).float()


def _head_values(model: torch.nn.Module, heads: TaskHeads) -> tuple[np.ndarray, np.ndarray]:
    """The heads on every lattice state: reward (2917, 3) and terminal value (2917,), 0 from LOST."""
    z = _latents(model, lattice_observations())
    eye = torch.eye(N_ACTIONS)
    with torch.inference_mode():
        reward = torch.stack([heads.predict_reward(z, eye[a].expand(len(z), -1)) for a in range(N_ACTIONS)], dim=1)
        value = heads.q_values(z, heads.act(z, 0.0, deterministic=True)).min(0).values
    rewards, values = np.zeros((N_STATES, N_ACTIONS)), np.zeros(N_STATES)
    rewards[:N_LATTICE], values[:N_LATTICE] = reward.double().numpy(), value.double().numpy()
    return rewards, values


class HeadsPlanner(LatticePlanner):
    """Receding-horizon DP over a model's lattice table with a task's learned reward and value (see the module
    docstring): the best ``horizon``-step return ``sum gamma^t r_hat + gamma^H V_hat`` of each first action;
    acting and tie-breaking are the zero-shot planner's."""

    def __init__(self, lattice: LatticeModel, rewards: np.ndarray, values: np.ndarray, horizon: int,
                 discount: float):
        # Not LatticePlanner's set-up, which tabulates the true reward: the heads' reward and value replace it.
        self.successor = lattice.successor
        self.reward = rewards
        self.discount = float(discount)
        value = values.copy()
        for _ in range(int(horizon) - 1):
            value = (rewards + self.discount * value[self.successor]).max(axis=1)
        self.last = value  # the best (H-1)-step return plus the terminal value, from each state

    def action_values(self, state: int, steps_left: int) -> np.ndarray:
        return self.reward[state] + self.discount * self.last[self.successor[state]]

    def tie_tolerance(self, top: float) -> float:
        return TIE_TOLERANCE * max(1.0, abs(top))  # learned values reach hundreds, summed in float64 from float32


def heads_return(model: torch.nn.Module, heads: TaskHeads, task: GridTask, horizon: int, discount: float,
                 seed: int = 0, stage: int = 0, lattice: LatticeModel | None = None) -> np.ndarray:
    """(EPISODES,) returns on ``task`` of planning with ``model`` and ``heads`` (:class:`HeadsPlanner`)."""
    lattice = lattice if lattice is not None else lattice_model(model_dynamics(model))
    rewards, values = _head_values(model, heads)
    planner = HeadsPlanner(lattice, rewards, values, horizon, discount)
    return play(lattice, task, EPISODES, seed=seed, stage=stage, planner=planner)


# ---- component errors ----------------------------------------------------------------------------------
def _rollout_hits(dynamics: Dynamics, probe: GridProbe, horizon: int) -> float:
    """Share of probe states whose H-step open-loop model rollout along optimal actions ends on the truth."""
    truth = _true_lattice().successor
    q = optimal_q(probe.task.name, probe.discount, probe.task.dense)
    state = probe.states.copy()
    z = torch.from_numpy(lattice_observations()[state])
    eye = torch.eye(N_ACTIONS)
    for _ in range(int(horizon)):
        action = q[state].argmax(axis=1)
        z = dynamics(z, eye[torch.from_numpy(action)])
        state = truth[state, action]
    predicted = state_index(decode_obs(z)).numpy()
    return float((predicted == state).mean())


def component_errors(model: torch.nn.Module, heads: TaskHeads | None, probe: GridProbe,
                     horizon: int) -> dict[str, float]:
    """Every component measure but the planning return, of ``model`` with task ``probe.task``'s ``heads``
    (None: a model without heads, only the dynamics are measured)."""
    dynamics = model_dynamics(model)
    obs = torch.from_numpy(probe.obs)
    predicted = dynamics(obs, torch.from_numpy(probe.actions))
    exact = state_index(decode_obs(predicted)) == state_index(decode_obs(torch.from_numpy(probe.next_obs)))
    out = {"dynamics_1step": float(exact.double().mean()),
           "dynamics_hstep": _rollout_hits(dynamics, probe, horizon)}
    if heads is None:
        return out
    z = _latents(model, obs)
    actions = torch.from_numpy(probe.actions)
    with torch.inference_mode():
        reward = heads.predict_reward(z, actions).double().numpy()
        q = heads.q_values(z, actions).min(0).values.double().numpy()
        chosen = heads.act(z[::N_ACTIONS], 0.0, deterministic=True).argmax(dim=1).numpy()
    optimal = probe.optimal.reshape(-1, N_ACTIONS)
    out["reward_error"] = float(np.abs(reward - probe.reward).mean())
    out["value_error"] = float(np.abs(q - probe.q_star).mean() / max(np.abs(probe.q_star).mean(), 1e-12))
    out["value_order"] = rank_correlation(q, probe.q_star)
    out["policy_agreement"] = float(optimal[np.arange(len(chosen)), chosen].mean())
    return out


def _ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 0..n-1 of ``values``, ties sharing their mean rank."""
    order = np.argsort(values, kind="stable")
    ranks = np.empty(len(values))
    ranks[order] = np.arange(len(values))
    _, tie, counts = np.unique(values, return_inverse=True, return_counts=True)
    return np.bincount(tie, weights=ranks)[tie] / counts[tie]


def rank_correlation(values: np.ndarray, reference: np.ndarray) -> float:
    """Spearman's rank correlation of two equally long arrays; 0.0 when either is constant (it orders nothing)."""
    a, b = _ranks(np.asarray(values, dtype=np.float64)), _ranks(np.asarray(reference, dtype=np.float64))
    a, b = a - a.mean(), b - b.mean()
    scale = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum() / scale) if scale > 0 else 0.0


# ---- the refit -----------------------------------------------------------------------------------------
def _refit_batch(probe: GridProbe, horizon: int, generator: np.random.Generator) -> Batch:
    """REFIT_BATCH (H+1)-step sequences from probe states along random actions, through the true dynamics."""
    lattice = _true_lattice()
    reward = lattice.rewards(probe.task)
    state = probe.states[generator.integers(len(probe.states), size=REFIT_BATCH)]
    obs = lattice_observations()
    eye = np.eye(N_ACTIONS, dtype=np.float32)
    start = obs[state]
    actions, rewards, following = [], [], []
    for _ in range(int(horizon) + 1):
        action = generator.integers(N_ACTIONS, size=REFIT_BATCH)
        rewards.append(reward[state, action])
        state = lattice.successor[state, action]
        actions.append(eye[action])
        following.append(obs[state])
    return Batch(obs=torch.from_numpy(start), actions=torch.from_numpy(np.stack(actions)),
                 rewards=torch.from_numpy(np.stack(rewards).astype(np.float32)),
                 next_obs=torch.from_numpy(np.stack(following)), weights=torch.ones(REFIT_BATCH),
                 indices=np.zeros(REFIT_BATCH, dtype=np.int64))


def refit_heads(model: torch.nn.Module, heads: TaskHeads, probe: GridProbe, cfg: AgentConfig,
                updates: int = REFIT_UPDATES, seed: int = 0, lr_decay: float = REFIT_LR_DECAY) -> TaskHeads:
    """A copy of ``heads`` trained on ``probe``'s task over the frozen ``model`` (see the module docstring), its
    learning rate decaying linearly from ``cfg.lr`` to ``lr_decay * cfg.lr`` (1: constant).

    Raises:
        RuntimeError: the model's weights changed (they cannot, by construction; checked all the same).
    """
    before = {k: v.detach().clone() for k, v in model.state_dict().items()}
    frozen = torch.optim.SGD(model.parameters(), lr=0.0)  # never stepped: train_world_model=False
    cfg = with_speed(cfg, precision="float32", compile="false")
    cfg = dataclasses.replace(cfg, tdmpc=dataclasses.replace(cfg.tdmpc, lr_final=cfg.lr * lr_decay,
                                                             lr_schedule_steps=max(int(updates) - 1, 1)))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        agent = Agent(model, frozen, cfg, discrete=True)
        agent.heads.load_state_dict(heads.state_dict())
        generator = np.random.default_rng(seed)
        for step in range(int(updates)):
            agent.update(_refit_batch(probe, cfg.tdmpc.horizon, generator), step, train_world_model=False)
    for key, value in model.state_dict().items():
        if not torch.equal(value, before[key]):
            raise RuntimeError(f"the refit changed the world model's {key}; it must only train heads")
    return agent.heads


# ---- a run ---------------------------------------------------------------------------------------------
def _rows_note(kind: str) -> str:
    if capabilities_of(kind).task_heads:
        return ""
    return f"agent.kind={kind} has no task heads apart from its world model: only the dynamics are measured"


@dataclass
class RunStages:
    """A grid run's finished stages as the component measures read them: stage N's world model (with its
    lattice table) and the heads saved at its end (None for an agent kind without task heads)."""

    cfg: Any
    checkpoints: list
    agent_configs: list[AgentConfig]
    models: list[torch.nn.Module]
    heads: list[TaskHeads | None]
    lattices: list[LatticeModel]

    @property
    def horizon(self) -> int:
        return int(self.cfg.agent.tdmpc.horizon)

    @property
    def discount(self) -> float:
        return float(self.cfg.agent.tdmpc.discount)

    def probe(self, k: int) -> GridProbe:
        return grid_probe(self.checkpoints[k].task, self.discount, self.cfg.env.dense_reward)

    @property
    def refit_updates(self) -> int:
        """The swap test's refit budget for this run: a tenth of a task's learner steps, at most REFIT_UPDATES."""
        learner_steps = self.cfg.train.learner_steps_per_task or self.cfg.train.steps_per_task
        return max(1, min(REFIT_UPDATES, int(learner_steps) // 10))

    def optimum(self, k: int) -> float:
        """Task k's DP-optimal return (the denominator of every fraction of the swap test)."""
        return _optimum(self.probe(k).task)

    def planned_return(self, n: int, heads: TaskHeads, k: int) -> float:
        """The mean return on task k of planning with stage n's model and ``heads`` (:func:`heads_return`)."""
        returns = heads_return(self.models[n], heads, self.probe(k).task, self.horizon, self.discount,
                               seed=self.cfg.train.seed, stage=self.checkpoints[n].stage, lattice=self.lattices[n])
        return float(returns.mean())

    def refit_seeds(self, draws: int = REFIT_DRAWS) -> list[int]:
        """The seeds of the swap test's refits of this run (their own: no two runs' seeds share one)."""
        return [self.cfg.train.seed * draws + draw for draw in range(draws)]


def load_run_stages(run_dir: str | Path, device: str = "cpu") -> RunStages:
    """A grid run's finished stages (:class:`RunStages`).

    Raises:
        ComponentsError: not a grid run, or no finished task.
        drago.training.checkpoint.CheckpointError: a corrupt checkpoint.
    """
    from drago.training.checkpoint import load_task_checkpoint

    cfg, checkpoints = components_checkpoints(Path(run_dir))
    loaded = [load_task_checkpoint(c.path, device) for c in checkpoints]
    models = [c.world_model.eval() for c in loaded]
    heads: list[TaskHeads | None] = []
    for c in loaded:
        if not capabilities_of(cfg.agent.kind).task_heads or "learner" not in c.data:
            heads.append(None)
            continue
        h = TaskHeads(c.spec.obs_dim, c.spec.action_dim, c.config.agent.tdmpc.mlp_dim, True,
                      fast_tanh=c.config.agent.tdmpc.fast_tanh)
        h.load_state_dict(c.data["learner"])
        heads.append(h.eval())
    return RunStages(cfg, checkpoints, [c.config.agent for c in loaded], models, heads,
                     [lattice_model(model_dynamics(model)) for model in models])


def components_of_run(run_dir: str | Path, zero_shot_rows: Sequence[dict[str, Any]] = (),
                      device: str = "cpu") -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The component rows (stage x task x component) and the swap-test rows of a grid run's checkpoints.

    ``zero_shot_rows`` (the run's zero-shot matrix, at each task's own reward) fill the swap test's
    true-reward column; without them it stays empty.

    Raises:
        ComponentsError: not a grid run, or no finished task.
        drago.training.checkpoint.CheckpointError: a corrupt checkpoint.
    """
    stages = load_run_stages(run_dir, device)
    cfg, checkpoints, models, heads = stages.cfg, stages.checkpoints, stages.models, stages.heads
    name = f"{cfg.method.name}/seed{cfg.train.seed}"
    kind = cfg.agent.kind
    horizon = stages.horizon
    true_reward = {(int(r["stage"]), r["task"]): r for r in zero_shot_rows}
    rows, swaps = [], []
    own_return: dict[tuple[int, int], float] = {}
    for n, checkpoint in enumerate(checkpoints):
        for k in range(n + 1):
            if task_room(checkpoints[k].task) is None:
                continue
            probe = stages.probe(k)
            base = {"run": name, "method": cfg.method.name, "seed": cfg.train.seed, "stage": checkpoint.stage,
                    "stage_task": checkpoint.task, "task": checkpoints[k].task}
            measures = component_errors(models[n], heads[k], probe, horizon)
            if heads[k] is not None:
                own_return[(n, k)] = stages.planned_return(n, heads[k], k)
                measures["return_own_heads"] = own_return[(n, k)] / stages.optimum(k)
            note = _rows_note(kind)
            rows += [dict(base, component=c, value=measures.get(c, math.nan), note="" if c in measures else note)
                     for c in COMPONENTS]
    for n, checkpoint in enumerate(checkpoints):
        for k in range(n):
            task = checkpoints[k].task
            if heads[k] is None or task_room(task) is None:
                continue
            probe = stages.probe(k)
            refits = [stages.planned_return(n, refit_heads(models[n], heads[k], probe, stages.agent_configs[n],
                                                           updates=stages.refit_updates, seed=seed), k)
                      for seed in stages.refit_seeds()]
            zero = true_reward.get((checkpoint.stage, task))
            swaps.append({"run": name, "method": cfg.method.name, "seed": cfg.train.seed,
                          "stage": checkpoint.stage, "stage_task": checkpoint.task, "task": task,
                          "optimum": stages.optimum(k), "saved": own_return[(k, k)], "moved": own_return[(n, k)],
                          "refit": float(np.mean(refits)),
                          "true_reward": "" if zero is None else float(zero["return"]),
                          "refit_updates": stages.refit_updates, "refit_min": min(refits), "refit_max": max(refits),
                          "refit_draws": len(refits)})
    return rows, swaps


def _optimum(task: GridTask) -> float:
    from drago.envs import task_optimum

    return float(task_optimum(GRID_DOMAIN, task.name, task.dense))


def components_checkpoints(run_dir: str | Path):
    """The run's config and finished checkpoints, refusing a run the component measures cannot serve (cheap:
    files only, so a command given several runs refuses a bad one before measuring any)."""
    return _run_checkpoints(Path(run_dir), ComponentsError, lambda c: None if exact_world(c.env.domain) else
                            "component retention is measured on the grid only for now (domains on an exact world)")


def evaluate_components(run_dir: str | Path) -> tuple[list[dict[str, Any]], list[Path]]:
    """Measure a grid run's components, swap test and costs into ``components.csv``, ``swap.csv`` and
    ``costs.csv`` in the run directory (``drago eval components``); returns the swap rows and the files.

    The swap test's true-reward column is the run's ``zero_shot.csv`` where it has the training rooms at the
    evaluation's defaults, else those rows are computed (and not written).
    """
    from drago.eval.costs import COSTS_FILE, costs_of_run, write_costs_csv
    from drago.eval.zero_shot import zero_shot_matrix

    run_dir = Path(run_dir)
    cfg, checkpoints = components_checkpoints(run_dir)
    rooms = [c.task for c in checkpoints if task_room(c.task) is not None]
    zero_shot = zero_shot_matrix(run_dir, tasks=sorted(set(rooms), key=rooms.index)) if rooms else []
    rows, swaps = components_of_run(run_dir, zero_shot)
    written = [write_components_csv(rows, run_dir / COMPONENTS_FILE), write_swap_csv(swaps, run_dir / SWAP_FILE),
               write_costs_csv(costs_of_run(run_dir), run_dir / COSTS_FILE)]
    return swaps, written


def write_components_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    return write_rows_csv(rows, COMPONENT_COLUMNS, path)


def write_swap_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    return write_rows_csv(rows, SWAP_COLUMNS, path)
