"""Agents are reached through one protocol and asked what they can do (docs: design, "The agent protocol").

A third agent kind, registered from outside drago as a plug-in would, trains a continual sequence with
methods that ask for nothing it lacks, and is refused in one line by a method that needs what it lacks.
"""

from __future__ import annotations

import ast
import contextlib
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

import drago
from drago.agent.protocol import (PETS_CAPABILITIES, TDMPC_CAPABILITIES, AgentCapabilities, AgentKind, ContinualAgent,
                                  ContinualWorldModel, agent_kinds, capabilities_of, unregister_agent_kind)
from drago.config import ConfigError


class DeltaModel(nn.Module):
    """A linear model of the next observation's change: the smallest world model the methods can carry."""

    def __init__(self, obs_dim: int, action_dim: int):
        super().__init__()
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.delta = nn.Linear(obs_dim + action_dim, obs_dim)

    def encode(self, obs: torch.Tensor) -> torch.Tensor:
        return obs

    def raw_next(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return z + self.delta(torch.cat((z, action), dim=-1))

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.raw_next(z, action).clamp(-1.0, 1.0)


class RandomShooter:
    """Acts at random and learns only its world model, by one-step squared error: nothing of TD-MPC's."""

    capabilities = AgentCapabilities()

    def __init__(self, world_model: DeltaModel, world_optimizer: torch.optim.Optimizer | None):
        self.world_model, self.world_optimizer = world_model, world_optimizer
        self.device = torch.device("cpu")
        self.updates = 0

    def autocast(self):
        return contextlib.nullcontext()

    def act(self, obs, step, eval_mode, first_step, bonus=None):
        rows = np.atleast_2d(obs).shape[0]
        choice = torch.randint(self.world_model.action_dim, (rows,))
        action = nn.functional.one_hot(choice, self.world_model.action_dim).float().numpy()
        return action if np.ndim(obs) == 2 else action[0]

    def random_action(self, rng):
        return np.eye(self.world_model.action_dim, dtype=np.float32)[rng.integers(self.world_model.action_dim)]

    def update(self, batch, step, train_world_model=True, policy_rows=None, world_model_loss=None):
        predicted = self.world_model(batch.obs, batch.actions[0])
        error = (predicted - batch.next_obs[0]).pow(2).mean(-1)
        if train_world_model:
            loss = error.mean() + (world_model_loss() if world_model_loss is not None else 0.0)
            self.world_optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.world_optimizer.step()
        self.updates += 1
        rows = batch.obs.shape[0] if policy_rows is None else policy_rows
        return {"model_error": error.mean().detach(), "mean_prediction_score": -torch.log(error.mean().detach() + 1e-8),
                "priority": torch.ones(rows)}

    def task_state(self):
        return {"learner": {"updates": self.updates}}

    def load_task_state(self, state):
        self.updates = int(state["learner"]["updates"])

    def trained_modules(self):
        return {}

    def state_dict(self):
        return {"updates": self.updates}

    def load_state_dict(self, state):
        self.updates = int(state["updates"])


RANDOM_SHOOTER = AgentKind(
    name="random-shooter", description="random actions over a linear delta model (a test's plug-in)",
    capabilities=RandomShooter.capabilities,
    build_world_model=lambda cfg, spec, device: DeltaModel(spec.obs_dim, spec.action_dim).to(device),
    build_world_optimizer=lambda cfg, model: torch.optim.Adam(model.parameters(), lr=cfg.agent.lr),
    build_agent=lambda cfg, spec, model, optimizer, task=None, reviewer=False: RandomShooter(model, optimizer),
    replay_horizon=lambda cfg: 1)


@pytest.fixture
def random_shooter() -> Iterator[AgentKind]:
    drago.register_agent_kind(RANDOM_SHOOTER)
    try:
        yield RANDOM_SHOOTER
    finally:
        unregister_agent_kind(RANDOM_SHOOTER.name)


def test_both_built_in_agents_implement_the_protocol():
    from drago.agent.factory import build_agent, build_world_model, build_world_optimizer

    for kind, capabilities in (("tdmpc", TDMPC_CAPABILITIES), ("pets", PETS_CAPABILITIES)):
        cfg = drago.load_config("smoke", [f"agent.kind={kind}"])
        spec = drago.get_domain(cfg.env.domain).env_spec()
        model = build_world_model(cfg, spec)
        agent = build_agent(cfg, spec, model, build_world_optimizer(cfg, model), task="room1")
        assert isinstance(agent, ContinualAgent) and isinstance(model, ContinualWorldModel)
        assert agent.capabilities == capabilities == capabilities_of(kind)
    assert not hasattr(agent, "heads") and not hasattr(agent, "rollout")  # PETS carries no TD-MPC shims


@pytest.mark.slow
@pytest.mark.parametrize("method", ["continual", "drago"])
def test_a_plug_in_agent_kind_trains_a_sequence_without_editing_drago(random_shooter, method, tmp_path):
    assert "random-shooter" in agent_kinds()
    cfg = drago.load_config("smoke", ["agent.kind=random-shooter", "env.tasks=[room1,room2]"], method=method)
    run = drago.train(cfg, tmp_path / method, progress=False)
    summary = json.loads((Path(run.path) / "summary.json").read_text())
    assert [t["name"] for t in summary["tasks"]] == ["room1", "room2"]
    ckpt = torch.load(Path(run.path) / "checkpoints" / "task2_room2.pt", weights_only=False)
    assert ckpt["learner"]["updates"] > 0  # the kind's own task state, as it returned it
    assert set(ckpt["world_model"]) == {"delta.weight", "delta.bias"}


def test_a_method_needing_what_the_kind_lacks_refuses_it_in_one_line(random_shooter):
    with pytest.raises(ConfigError) as err:
        drago.load_config("smoke", ["agent.kind=random-shooter"], method="curiosity")
    assert "needs a learned value" in str(err.value) and "agent.kind=random-shooter" in str(err.value)
    assert len(str(err.value).splitlines()) == 1


def test_an_unknown_agent_kind_names_the_registered_ones(random_shooter):
    with pytest.raises(ConfigError, match="unknown agent.kind 'tdmpc2'; valid choices: tdmpc, pets, random-shooter"):
        drago.load_config("smoke", ["agent.kind=tdmpc2"])


def test_a_bad_kind_is_refused_at_registration():
    with pytest.raises(ConfigError, match="needs a drago.AgentKind"):
        drago.register_agent_kind("random-shooter")
    with pytest.raises(ConfigError, match="already registered"):
        drago.register_agent_kind(AgentKind(**{**RANDOM_SHOOTER.__dict__, "name": "tdmpc"}))


PACKAGE = Path(drago.__file__).resolve().parent


def kind_name_comparisons(source: str, kinds: set[str]) -> list[int]:
    """Lines of ``source`` that compare a value with an agent kind's name (``kind == "pets"``, ``in ("tdmpc",)``).

    Data keyed by a kind (the paper's numbers for its TD-MPC agent) is not a comparison: a plug-in kind simply
    has no entry there."""
    def names(node):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node.value
        elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            for element in node.elts:
                yield from names(element)

    return [node.lineno for node in ast.walk(ast.parse(source)) if isinstance(node, ast.Compare)
            and any(name in kinds for operand in (node.left, *node.comparators) for name in names(operand))]


def test_no_agent_kind_is_compared_outside_the_agent_layer():
    kinds = set(agent_kinds())
    found = [f"{path.relative_to(PACKAGE.parent)}:{line}" for path in sorted(PACKAGE.rglob("*.py"))
             if path.relative_to(PACKAGE).parts[0] != "agent"
             for line in kind_name_comparisons(path.read_text(), kinds)]
    assert not found, "ask the agent's capabilities instead of naming its kind: " + ", ".join(found)


def test_the_kind_scan_sees_a_comparison():
    assert kind_name_comparisons('if cfg.agent.kind != "tdmpc":\n    pass\nx = kind in ("pets", "other")\n',
                                 {"tdmpc", "pets"}) == [1, 3]
    assert kind_name_comparisons('PAPER = {("tdmpc", "drago"): 1}\n', {"tdmpc", "pets"}) == []
