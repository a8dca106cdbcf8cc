"""Domains are asked what they can do, never named (docs: design, "Capabilities").

Outside ``drago/envs/`` no code compares a domain's name: what the grid gets (exact coverage, visitation
maps, zero-shot planning, a reward a planner may be told, the paper's transfer cases) follows from what a
domain declares, so a plug-in domain that declares the same gets the same without editing drago.
"""

from __future__ import annotations

import ast
import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from drago.config import ConfigError, load_config
from drago.envs import (EnvSpec, available_domains, exact_world, get_domain, register_domain, task_optimum,
                        unregister_domain)
from drago.envs.domain import Domain, DomainError
from drago.training.heldout_sets import HeldoutRecorder
from drago.training.transfer import paper_cases
from drago.training.visitation import VisitationRecorder

PACKAGE = Path(__file__).resolve().parents[1] / "drago"


def _names(node: ast.AST) -> Iterator[str]:
    """String constants a comparison operand holds, alone or in a tuple, list or set literal."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        yield node.value
    elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        for element in node.elts:
            yield from _names(element)


def domain_name_uses(source: str, domains: set[str]) -> list[int]:
    """Lines of ``source`` that compare a value with a domain's name, look one up by it, or key by it."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            if any(name in domains for operand in operands for name in _names(operand)) or any(
                    isinstance(operand, ast.Name) and operand.id.endswith("_DOMAIN") for operand in operands):
                lines.append(node.lineno)
        elif isinstance(node, ast.Subscript) and any(name in domains for name in _names(node.slice)):
            lines.append(node.lineno)
        elif isinstance(node, ast.Dict) and any(key is not None and name in domains
                                                for key in node.keys for name in _names(key)):
            lines.append(node.lineno)
    return lines


def test_no_domain_name_is_compared_outside_envs():
    domains = {*available_domains(), "dmc"}
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.relative_to(PACKAGE).parts[0] == "envs":
            continue
        found += [f"{path.relative_to(PACKAGE.parent)}:{line}"
                  for line in domain_name_uses(path.read_text(), domains)]
    assert not found, "ask the domain's capabilities instead of naming it: " + ", ".join(found)


def test_the_scan_sees_each_kind_of_domain_name_use():
    domains = {"minigrid", "cheetah"}
    assert domain_name_uses('if cfg.env.domain == "minigrid":\n    pass', domains) == [1]
    assert domain_name_uses('x = d in ("cheetah", "walker")', domains) == [1]
    assert domain_name_uses('cases = CASES["minigrid"]', domains) == [1]
    assert domain_name_uses('CASES = {"minigrid": ()}', domains) == [1]
    assert domain_name_uses('if domain != GRID_DOMAIN:\n    pass', domains) == [1]
    assert domain_name_uses('domain: str = "minigrid"\nmake_env(GRID_DOMAIN, "room1")', domains) == []


@contextlib.contextmanager
def registered(domain: Domain) -> Iterator[Domain]:
    register_domain(domain)
    try:
        yield domain
    finally:
        unregister_domain(domain.name)


def rooms_without_the_name(**capabilities) -> Domain:
    """The grid's dynamics and two of its rooms under another name, declaring what it is given."""
    grid = get_domain("minigrid")
    return Domain(name="my-rooms", spec=EnvSpec("my-rooms", obs_dim=3, action_dim=3, discrete=True),
                  tasks={"room1": "room 1, dense", "room2": "room 2, dense"}, make=grid.make, episode_length=100,
                  optimum=grid.optimum, tabular=True, dense_reward=True, **capabilities)


def config_on(domain: str, *overrides: str):
    return load_config("smoke", [f"env.domain={domain}", "env.tasks=[room1,room2]", *overrides])


def test_a_plug_in_domain_on_the_four_rooms_world_gets_the_grids_evaluations():
    grid = get_domain("minigrid")
    with registered(rooms_without_the_name(exact_world="four-rooms", known_reward=grid.known_reward,
                                           transfer_cases=(("room2", 1),))):
        cfg = config_on("my-rooms")
        assert exact_world("my-rooms") == "four-rooms"
        assert VisitationRecorder.wanted(cfg)  # visitation maps of the grid
        assert not HeldoutRecorder.wanted(cfg)  # exact coverage, not sampled held-out sets
        assert paper_cases("my-rooms") == (("room2", 1),)
        assert task_optimum("my-rooms", "room1") == task_optimum("minigrid", "room1")
        config_on("my-rooms", "agent.kind=pets", "agent.pets.reward=known")  # a planner may be told the reward
        with pytest.raises(ConfigError, match="must be 1 for the grid and other tabular domains"):
            config_on("my-rooms", "env.action_repeat=2")


def test_a_domain_that_declares_nothing_gets_none_of_it_in_one_line():
    with registered(rooms_without_the_name()):
        cfg = config_on("my-rooms", "train.heldout_episodes=2")
        assert exact_world("my-rooms") is None
        assert not VisitationRecorder.wanted(cfg) and HeldoutRecorder.wanted(cfg)
        with pytest.raises(Exception, match="declares no transfer cases; domains with cases: minigrid"):
            paper_cases("my-rooms")
        with pytest.raises(ConfigError, match="my-rooms declares none: use agent.pets.reward=learned") as err:
            config_on("my-rooms", "agent.kind=pets", "agent.pets.reward=known")
        assert len(str(err.value).splitlines()) == 1


def test_the_grids_known_reward_pays_the_goal_as_the_env_does():
    from drago.envs import make_env
    from drago.envs.fourrooms import decode_observation

    env = make_env("minigrid", "room1")
    obs, _ = env.reset(seed=0)
    reward = get_domain("minigrid").known_reward("room1", None)
    paid = []
    for action in [2] * 6 + [1] + [2] * 6:
        one_hot = torch.nn.functional.one_hot(torch.tensor([action]), 3).float()
        next_obs, env_reward, terminated, truncated, _ = env.step(one_hot[0].numpy())
        known = reward(torch.tensor(obs)[None], one_hot, torch.tensor(next_obs)[None])
        paid.append((float(known[0]), float(env_reward), decode_observation(next_obs)))
        obs = next_obs
        if terminated or truncated:
            break
    assert all(abs(known - env_reward) < 1e-9 for known, env_reward, _ in paid), paid


@pytest.mark.parametrize("capabilities, words", [
    ({"transfer_cases": (("room1", 0),)}, "must be (task name, stage K >= 1)"),
    ({"transfer_cases": (("room 1", 1),)}, "must be (task name, stage K >= 1)"),
    ({"dense_by_default": {"room9": True}}, "unknown tasks ['room9']"),
    ({"known_reward": "room1"}, "known_reward must be None or a callable"),
    ({"exact_world": "nine-rooms"}, "exact_world must be None or one of four-rooms"),
])
def test_a_bad_capability_is_one_line_naming_it(capabilities, words):
    with pytest.raises(DomainError) as err:
        rooms_without_the_name(**capabilities)
    assert words in str(err.value) and len(str(err.value).splitlines()) == 1
