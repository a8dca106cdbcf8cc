"""Which part forgot (docs: Evaluation, "Which part forgot"): component measures and the swap test on hand-made
models of the grid, and the byte accounting of what each method carries across a task boundary."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drago.agent.networks import TaskHeads
from drago.envs import task_optimum
from drago.eval.components import (REFIT_DRAWS, ComponentsError, component_errors, grid_probe, heads_return,
                                   optimal_q, rank_correlation, refit_heads)
from drago.eval.costs import carried_bytes
from drago.eval.zero_shot import true_dynamics
from helpers import tdmpc_config

CFG = tdmpc_config(mlp_dim=64, horizon=5)


class TrueModel(torch.nn.Module):
    """The grid's exact dynamics in the world model's shape: the latent is the observation."""

    obs_dim = action_dim = 3

    def __init__(self):
        super().__init__()
        self.unused = torch.nn.Parameter(torch.zeros(1))  # something the refit could wrongly train

    def encode(self, obs: torch.Tensor) -> torch.Tensor:
        return obs

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return true_dynamics(z, action)


class FrozenInPlace(TrueModel):
    """A corrupted model: it believes no action ever moves the agent."""

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return z


def fraction(model, heads, task="room1") -> float:
    probe = grid_probe(task, CFG.tdmpc.discount)
    returns = heads_return(model, heads, probe.task, CFG.tdmpc.horizon, CFG.tdmpc.discount)
    return float(returns.mean()) / task_optimum("minigrid", task)


@pytest.fixture(scope="module")
def learned_heads() -> TaskHeads:
    """Heads trained on room 1 over the true model (the refit from random weights): what "saved after k" holds."""
    torch.manual_seed(0)
    heads = TaskHeads(3, 3, CFG.tdmpc.mlp_dim, True)
    return refit_heads(TrueModel(), heads, grid_probe("room1", CFG.tdmpc.discount), CFG)


def test_the_probe_is_room_one_with_its_dp_values():
    probe = grid_probe("room1", CFG.tdmpc.discount)
    assert len(probe.obs) == len(probe.states) * 3 and len(probe.states) % 4 == 0
    # The dense reward pays 3 on the goal cell and repeatedly while the agent stays there: Q* there is 3 / (1 - γ).
    assert probe.q_star.max() == pytest.approx(3 / (1 - CFG.tdmpc.discount), rel=1e-6)
    # Bellman optimality holds on the probe rows: Q*(s, a) = r + γ max Q*(s', ·).
    q = optimal_q("room1", CFG.tdmpc.discount)
    from drago.eval.zero_shot import decode_obs, state_index
    following = state_index(decode_obs(torch.from_numpy(probe.next_obs))).numpy()
    np.testing.assert_allclose(probe.q_star, probe.reward + CFG.tdmpc.discount * q[following].max(axis=1), atol=1e-6)
    assert 0 < probe.optimal.mean() < 1
    with pytest.raises(ComponentsError, match="training rooms"):
        grid_probe("room1to2", CFG.tdmpc.discount)


def test_the_value_order_reads_the_critic_s_ranking_whatever_its_scale():
    q_star = grid_probe("room1", 0.99).q_star
    assert rank_correlation(0.01 * q_star - 5.0, q_star) == pytest.approx(1.0)  # far off in scale, same order
    assert rank_correlation(-q_star, q_star) == pytest.approx(-1.0)
    assert rank_correlation(np.zeros_like(q_star), q_star) == 0.0  # a constant critic orders nothing
    # Ties share their mean rank: Spearman's rho of (1, 2, 2, 3) and (1, 2, 3, 4) is 0.9487 (closed form).
    assert rank_correlation(np.array([1.0, 2.0, 2.0, 3.0]), np.arange(4.0)) == pytest.approx(3 / np.sqrt(10))


def test_a_perfect_model_scores_no_dynamics_error():
    measures = component_errors(TrueModel(), None, grid_probe("room2", CFG.tdmpc.discount), CFG.tdmpc.horizon)
    assert measures == {"dynamics_1step": 1.0, "dynamics_hstep": 1.0}
    broken = component_errors(FrozenInPlace(), None, grid_probe("room2", CFG.tdmpc.discount), CFG.tdmpc.horizon)
    assert broken["dynamics_1step"] < 0.1 and broken["dynamics_hstep"] == 0.0


@pytest.mark.slow
def test_heads_that_fit_the_task_plan_well_over_a_perfect_model(learned_heads):
    measures = component_errors(TrueModel(), learned_heads, grid_probe("room1", CFG.tdmpc.discount), CFG.tdmpc.horizon)
    assert measures["reward_error"] < 0.15 and measures["policy_agreement"] > 0.4
    assert fraction(TrueModel(), learned_heads) > 0.6


@pytest.mark.slow
def test_corrupted_heads_are_recovered_by_the_refit_so_the_loss_is_the_heads(learned_heads):
    torch.manual_seed(1)
    corrupted = TaskHeads(3, 3, CFG.tdmpc.mlp_dim, True)  # the model is perfect, the heads know nothing
    saved, moved = fraction(TrueModel(), learned_heads), fraction(TrueModel(), corrupted)
    refit = refit_heads(TrueModel(), corrupted, grid_probe("room1", CFG.tdmpc.discount), CFG, seed=2)
    recovered = fraction(TrueModel(), refit)
    assert moved < 0.1 < saved
    assert recovered > 0.6, "a perfect model must support the task once the heads are refit"


@pytest.mark.slow
def test_corrupted_dynamics_are_not_recovered_by_the_refit_so_the_loss_is_the_model(learned_heads):
    model = FrozenInPlace()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    moved = fraction(model, learned_heads)
    refit = refit_heads(model, learned_heads, grid_probe("room1", CFG.tdmpc.discount), CFG, seed=2)
    assert moved < 0.1 and fraction(model, refit) < 0.1
    assert all(torch.equal(v, before[k]) for k, v in model.state_dict().items())  # the refit trains heads only


def test_byte_accounting_matches_the_state_dicts_each_method_keeps():
    world = torch.nn.Linear(6, 3)
    vae = torch.nn.Sequential(torch.nn.Linear(6, 4), torch.nn.Linear(4, 6))
    fisher = {name: torch.ones_like(p) for name, p in world.named_parameters()}
    reservoir = {"obs": torch.zeros(50, 3), "actions": torch.zeros(50, 3, dtype=torch.float64), "size": 50}
    world_bytes = sum(t.numel() * t.element_size() for t in world.state_dict().values())
    vae_bytes = sum(t.numel() * t.element_size() for t in vae.state_dict().values())
    drago = carried_bytes(world.state_dict(), {"vae": vae.state_dict(), "threshold": 9.5, "tasks_seen": 2})
    assert drago["world_model"] == world_bytes == 4 * (18 + 3) and drago["generator"] == vae_bytes
    ewc = carried_bytes(world.state_dict(), {"fisher": fisher, "anchor": world.state_dict(), "tasks": 1})
    assert ewc["fisher"] == ewc["anchor"] == world_bytes
    replay = carried_bytes(world.state_dict(), {"reservoir": reservoir})
    assert replay["raw_transitions"] == 50 * 3 * 4 + 50 * 3 * 8
    assert carried_bytes(world.state_dict(), {}) == {**dict.fromkeys(drago, 0), "world_model": world_bytes}


@pytest.mark.slow
def test_eval_components_writes_its_files_and_the_report_shows_them(tmp_path, capsys):
    from drago import cli

    tiny = ["train.steps_per_task=200", "agent.seed_steps=100", "train.checkpoint_freq=100",
            "train.tensorboard=false", "agent.tdmpc.mlp_dim=16", "agent.batch_size=16", "agent.tdmpc.iterations=1",
            "agent.tdmpc.num_samples=8", "agent.tdmpc.num_elites=2", "train.threads=1", "env.tasks=[room1,room2]"]
    run = tmp_path / "run"
    assert cli.main(["train", "smoke", "--method", "replay", "--out", str(run), "--no-progress", *tiny]) == 0
    capsys.readouterr()
    assert cli.main(["eval", "components", str(run)]) == 0
    out = capsys.readouterr().out
    assert "room1" in out and "saved" in out and f"wrote {run / 'swap.csv'}" in out
    import csv
    with (run / "components.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    # stage 1: room1; stage 2: room1 and room2; six parts each
    assert len(rows) == 3 * 7 and {r["component"] for r in rows} >= {"dynamics_1step", "return_own_heads"}
    with (run / "costs.csv").open() as handle:
        costs = list(csv.DictReader(handle))
    # replay is the one method that carries raw transitions of earlier tasks
    assert [r["raw_data"] for r in costs] == ["True", "True"] and int(costs[0]["bytes_raw_transitions"]) > 0
    with (run / "swap.csv").open() as handle:
        swaps = list(csv.DictReader(handle))
    # room1 after stage 2: the refit column is the mean of REFIT_DRAWS refits, between the lowest and highest
    assert len(swaps) == 1 and int(swaps[0]["refit_draws"]) == REFIT_DRAWS
    assert float(swaps[0]["refit_min"]) <= float(swaps[0]["refit"]) <= float(swaps[0]["refit_max"])
    assert cli.main(["report", str(run), "--out", str(tmp_path / "report")]) == 0
    page = (tmp_path / "report" / "report.md").read_text()
    assert "## The swap test" in page and "## What each method stores and spends" in page
    assert cli.main(["eval", "components", str(tmp_path)]) == 2
    assert "is not a drago run directory (no config.yaml)" in capsys.readouterr().err


def test_the_cost_table_marks_a_generator_no_task_trained():
    from drago.report.components import _cost_table

    def costs(vae_updates: int) -> list[dict]:
        return [{"bytes_world_model": 2_000_000, "bytes_generator": 500_000, "bytes_fisher": 0, "bytes_anchor": 0,
                 "bytes_raw_transitions": 0, "bytes_other": 0, "raw_data": False, "learner_env_steps": 10,
                 "reviewer_env_steps": 5, "learner_updates": 9, "reviewer_updates": 4, "vae_updates": vae_updates,
                 "cpu_s": 3600.0}]

    table = _cost_table({}, {"rehearsing": [costs(9)], "idle": [costs(0), costs(0)]}, {})
    carried = {row[0]: row[1] for row in table.rows}
    assert carried == {"rehearsing": "world model 2.00, generator 0.50",
                       "idle": "world model 2.00, generator 0.50 (never trained)"}
