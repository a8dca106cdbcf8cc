"""One TD-MPC agent: task heads over a shared world model, with its optimizers and planner state.

The world model and its optimizer are passed in, not owned: a continual method decides whether the
world model is fresh or carried over, and DRAGO's learner and reviewer share one of each.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from drago.agent.buffer import Batch
from drago.agent.losses import model_losses, policy_loss, rollout
from drago.agent.networks import TaskHeads, WorldModel, autocast, linear_schedule
from drago.agent.planner import (
    EAGER,
    Evaluator,
    PlanSettings,
    RewardBonus,
    imagine_step,
    plan_continuous,
    plan_discrete,
    terminal_value,
)
from drago.agent.protocol import TDMPC_CAPABILITIES
from drago.agent.speed import resolve_agent_speed, with_speed
from drago.config import AgentConfig


def _float32_bonus(bonus: RewardBonus) -> RewardBonus:
    """A count bonus evaluated outside autocast: classifier pseudo-counts divide by the small change of a
    probability across one update, which bfloat16 would round away."""
    def call(z: torch.Tensor) -> torch.Tensor:
        with torch.autocast(device_type=z.device.type, enabled=False):
            return bonus(z.float())

    return call


def random_action(rng: np.random.Generator, action_dim: int, discrete: bool,
                  probs: tuple[float, ...] = ()) -> np.ndarray:
    """A seed-phase action: uniform in [-1, 1], or a one-hot drawn with ``probs`` when they name every
    action (the grid's left, right, forward) and uniformly otherwise (any other discrete domain)."""
    if not discrete:
        return rng.uniform(-1.0, 1.0, size=action_dim).astype(np.float32)
    action = np.zeros(action_dim, dtype=np.float32)
    action[rng.choice(action_dim, p=np.asarray(probs) if len(probs) == action_dim else None)] = 1.0
    return action


class Agent:
    """TD-MPC heads (reward, policy, twin Q) trained and planned against a given world model.

    Args:
        world_model: the shared dynamics; this agent trains it only when asked to.
        world_optimizer: the optimizer of the world model's parameters (shared between agents).
        cfg: agent settings.
        discrete: one-hot actions (grid) or continuous actions in [-1, 1].
        reviewer: use the reviewer's PER priority (r + 2 + |TD errors|).
    """

    capabilities = TDMPC_CAPABILITIES

    def __init__(self, world_model: WorldModel, world_optimizer: torch.optim.Optimizer, cfg: AgentConfig,
                 discrete: bool, reviewer: bool = False):
        self.world_model = world_model
        self.world_optimizer = world_optimizer
        device = next(world_model.parameters()).device
        if "auto" in (cfg.tdmpc.precision, cfg.tdmpc.compile):
            # Built outside a run, which resolves both when it starts: the precision a run would choose here,
            # and eager, because compiling pays back only over a run's many thousand calls.
            compile_ = "false" if cfg.tdmpc.compile == "auto" else cfg.tdmpc.compile
            cfg = resolve_agent_speed(with_speed(cfg, compile=compile_), device)[0]
        self.cfg = cfg
        self.discrete = discrete
        self.reviewer = reviewer
        self.heads = TaskHeads(world_model.obs_dim, world_model.action_dim, cfg.tdmpc.mlp_dim, discrete,
                               fast_tanh=cfg.tdmpc.fast_tanh).to(device)
        # The policy has its own optimizer: the model loss never reaches it and the policy loss must
        # not move the critics.
        self.model_optimizer = torch.optim.Adam(
            [*self.heads.reward.parameters(), *self.heads.q.parameters()], lr=cfg.lr)
        self.policy_optimizer = torch.optim.Adam(self.heads.policy.parameters(), lr=cfg.lr)
        # CEM std floor, advanced by updates only (paper §2; docs: Design, the agent)
        self.std_floor = cfg.tdmpc.std_schedule_start
        self._warm_mean: torch.Tensor | None = None
        self.device = device
        # Optional torch.compile: the update's loss functions (their backward is compiled with them) and
        # one step of the planner's trajectory evaluation. Optimizer steps stay eager.
        self._model_losses, self._policy_loss, self._evaluator = model_losses, policy_loss, EAGER
        if cfg.tdmpc.compile == "true":
            self._model_losses, self._policy_loss = torch.compile(model_losses), torch.compile(policy_loss)
            self._evaluator = Evaluator(step=torch.compile(imagine_step), terminal=torch.compile(terminal_value))

    def autocast(self):
        """The context of this agent's forward passes: bfloat16 autocast when ``precision`` asks for it."""
        return autocast(self.device, self.cfg.tdmpc.precision)

    # ------------------------------------------------------------------ acting
    def planning_horizon(self, step: int) -> int:
        c = self.cfg.tdmpc
        return int(min(c.horizon, linear_schedule(1, c.horizon, c.horizon_schedule_steps, step)))

    def plan_settings(self, step: int) -> PlanSettings:
        c = self.cfg.tdmpc
        return PlanSettings(horizon=self.planning_horizon(step), iterations=c.iterations, num_samples=c.num_samples,
                            num_elites=c.num_elites, num_policy_trajectories=int(c.mixture_coef * c.num_samples),
                            temperature=c.temperature, momentum=c.momentum, discount=c.discount, use_q=c.use_q,
                            policy_std=c.min_std, min_std=self.std_floor, max_std=c.max_std,
                            elite_selection=c.elite_selection)

    @torch.no_grad()
    def act(self, obs: np.ndarray, step: int, eval_mode: bool, first_step: bool,
            bonus: RewardBonus | None = None) -> np.ndarray:
        """Plan one action for an observation (n,), or one for each of E observations (E, n) planned as a
        batch, e.g. evaluation episodes played side by side (numpy in, numpy out)."""
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        settings = self.plan_settings(step)
        if bonus is not None and self.cfg.tdmpc.precision != "float32":
            bonus = _float32_bonus(bonus)
        with self.autocast():
            if self.discrete:
                action = plan_discrete(self.world_model, self.heads, obs_t, settings, eval_mode, bonus,
                                       self._evaluator)
            else:
                warm = None if first_step else self._warm_mean
                action, self._warm_mean = plan_continuous(self.world_model, self.heads, obs_t, settings, eval_mode,
                                                          warm, bonus, self._evaluator)
        return action.cpu().numpy()  # the environment needs it on the host: the one sync per step

    def random_action(self, rng: np.random.Generator) -> np.ndarray:
        return random_action(rng, self.world_model.action_dim, self.discrete, self.cfg.random_action_probs)

    # ---------------------------------------------------------------- learning
    def rollout(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The world model's open-loop rollout z_0..z_H of these rows, with a graph (see :meth:`update`)."""
        with self.autocast():
            return rollout(self.world_model, obs, actions, self.cfg.tdmpc.horizon)

    def update(self, batch: Batch, step: int, train_world_model: bool = True, policy_rows: int | None = None,
               curiosity_coef: float = 0.0, world_model_loss: Callable[[], torch.Tensor] | None = None,
               latents: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """One gradient step of paper §2; docs: Design, the agent on a batch; returns metrics as tensors (no host sync).

        Args:
            batch: sequences from the replay buffer, rewards already final (relabelled if needed).
            step: task-local step index u, for the EMA period and the std schedule.
            train_world_model: include the consistency loss and step the world-model optimizer.
            policy_rows: the policy loss uses only the first rows (DRAGO's reviewer: its own data).
            curiosity_coef: prediction-error bonus inside the TD target (curiosity baseline).
            world_model_loss: an extra scalar loss on the world model, added to this step's objective
                when the world model is trained (EWC penalty, replayed old transitions, joint rehearsal).
            latents: this batch's :meth:`rollout` when the caller already has it: with its graph when
                ``train_world_model``, detached otherwise (DRAGO shares one rollout between its agents).
        """
        c = self.cfg.tdmpc
        self.std_floor = linear_schedule(c.std_schedule_start, c.min_std, c.std_schedule_steps, step)
        if c.lr_final is not None:
            lr = linear_schedule(self.cfg.lr, c.lr_final, c.lr_schedule_steps, step)
            for optimizer in (self.world_optimizer, self.model_optimizer, self.policy_optimizer):
                for group in optimizer.param_groups:
                    group["lr"] = lr
        with self.autocast():
            losses = self._model_losses(
                self.world_model, self.heads, batch.obs, batch.actions, batch.rewards, batch.next_obs,
                horizon=c.horizon, rho=c.rho, discount=c.discount, policy_std=c.min_std,
                consistency_coef=c.consistency_coef, reward_coef=c.reward_coef, value_coef=c.value_coef,
                first_step_qr_only=c.first_step_qr_only, train_world_model=train_world_model,
                reviewer_priority=self.reviewer, curiosity_coef=curiosity_coef, latents=latents)
        # Scaling by 1/H is TD-MPC's gradient scaling, written on the loss.
        weighted = (batch.weights * losses.total).mean() / c.horizon
        extra = None
        if train_world_model and world_model_loss is not None:
            extra = world_model_loss()
            weighted = weighted + extra

        params = [*self.heads.reward.parameters(), *self.heads.q.parameters()]
        self.model_optimizer.zero_grad(set_to_none=True)
        if train_world_model:
            self.world_optimizer.zero_grad(set_to_none=True)
            params += list(self.world_model.dynamics.parameters())
        weighted.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(params, c.grad_clip_norm)
        self.model_optimizer.step()
        if train_world_model:
            self.world_optimizer.step()

        rows = batch.obs.shape[0] if policy_rows is None else policy_rows
        with self.autocast():
            pi_loss = self._policy_loss(self.heads, losses.latents[:, :rows], c.rho, c.min_std)
        self.policy_optimizer.zero_grad(set_to_none=True)
        pi_params = list(self.heads.policy.parameters())
        grads = torch.autograd.grad(pi_loss, pi_params)
        for p, g in zip(pi_params, grads):
            p.grad = g
        pi_grad_norm = torch.nn.utils.clip_grad_norm_(pi_params, c.grad_clip_norm)
        self.policy_optimizer.step()

        if step % c.update_freq == 0:
            self.heads.ema_update(c.tau)
            if train_world_model:
                self.world_model.ema_update(c.tau)

        return {
            "consistency_loss": losses.consistency.mean().detach(),
            "reward_loss": losses.reward.mean().detach(),
            "value_loss": losses.value.mean().detach(),
            "pi_loss": pi_loss.detach(),
            "total_loss": losses.total.mean().detach(),
            "weighted_loss": weighted.detach(),
            "grad_norm": grad_norm.detach(),
            "pi_grad_norm": pi_grad_norm.detach(),
            "mean_prediction_score": losses.prediction_score.detach(),
            **({"world_model_extra_loss": extra.detach()} if extra is not None else {}),
            "priority": losses.priority[:rows],
        }

    # ------------------------------------------------------------- persistence
    def task_state(self) -> dict[str, Any]:
        """The heads and the CEM std floor, planning as at the task's end (a task checkpoint's learner)."""
        return {"learner": self.heads.state_dict(), "learner_std_floor": float(self.std_floor)}

    def load_task_state(self, state: dict[str, Any]) -> None:
        """:meth:`task_state` from a task checkpoint; one written before the floor was saved takes the floor's
        schedule at the task's last step (``state["steps"]``), the same up to one iteration's updates."""
        self.heads.load_state_dict(state["learner"])
        c = self.cfg.tdmpc
        self.std_floor = float(state.get("learner_std_floor", linear_schedule(
            c.std_schedule_start, c.min_std, c.std_schedule_steps, int(state.get("steps", 0)))))

    def trained_modules(self) -> dict[str, torch.nn.Module]:
        return {"learner heads": self.heads}

    def state_dict(self) -> dict[str, Any]:
        return {"heads": self.heads.state_dict(), "model_optimizer": self.model_optimizer.state_dict(),
                "policy_optimizer": self.policy_optimizer.state_dict(), "std_floor": self.std_floor}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.heads.load_state_dict(state["heads"])
        self.model_optimizer.load_state_dict(state["model_optimizer"])
        self.policy_optimizer.load_state_dict(state["policy_optimizer"])
        self.std_floor = state["std_floor"]
