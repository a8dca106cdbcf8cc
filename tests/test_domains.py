"""The domain registry: your own domains from gymnasium envs, the one-line errors, plug-ins found through
entry points, the dmc: family of stock dm_control tasks, and the built-in domains unchanged."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap

import gymnasium as gym
import numpy as np
import pytest

from drago.envs import (DOMAINS, Domain, DomainError, EnvSpec, available_domains, available_tasks, env_spec, get_domain,
                        gym_domain, is_domain, load_plugins, make_env, plugin_problems, register_domain, reward_variant,
                        task_descriptions, task_optimum, unregister_domain)
from drago.envs.builtin import pendulum_keep_low_reward

HAS_DMC = importlib.util.find_spec("dm_control") is not None
needs_dmc = pytest.mark.skipif(not HAS_DMC, reason="dm_control is not installed (pip install -e '.[dmc]')")


@pytest.fixture
def registered():
    """Register domains for one test; they are removed afterwards."""
    names: list[str] = []

    def add(domain: Domain, replace: bool = False) -> Domain:
        names.append(domain.name)
        return register_domain(domain, replace=replace)

    yield add
    for name in names:
        unregister_domain(name)


def one_line_error(excinfo) -> str:
    message = str(excinfo.value)
    assert isinstance(excinfo.value, ValueError) and "\n" not in message, message
    return message


# ---- the built-in domains are unchanged -------------------------------------------------------------
def test_builtin_domains_unchanged():
    assert DOMAINS == ("minigrid", "cheetah", "walker")
    assert available_domains()[:4] == ("minigrid", "cheetah", "walker", "pendulum")
    assert env_spec("minigrid") == EnvSpec("minigrid", 3, 3, True)
    assert env_spec("cheetah") == EnvSpec("cheetah", 17, 6, False)
    assert env_spec("walker") == EnvSpec("walker", 24, 6, False)
    assert available_tasks("minigrid") == ["room1", "room2", "room3", "room4", "room1to2", "room1to3", "room3to4"]
    assert available_tasks("cheetah") == ["cheetah-run", "cheetah-jump", "cheetah-run-backwards",
                                          "cheetah-jump-and-run", "cheetah-jump-and-run-backwards"]
    assert available_tasks("walker") == ["walker-stand", "walker-walk", "walker-run", "walker-walk-backwards",
                                         "walker-run-backwards"]
    assert task_descriptions("minigrid")[0] == ("room1",
                                                "training task 1, top-left room: (1, 1) -> (8, 12); dense reward")
    assert task_descriptions("cheetah")[0] == ("cheetah-run",
                                               "training task 1; transfer target; reward clip(vx/10, 0, 1)")
    assert task_optimum("minigrid", "room1") == pytest.approx(250.9, abs=0.05)
    assert task_optimum("cheetah", "cheetah-run") is None
    grid = get_domain("minigrid")
    assert grid.tabular and grid.dense_reward and grid.sequences["fourrooms"] == ("room1", "room2", "room3", "room4")
    assert not get_domain("cheetah").tabular and get_domain("walker").action_repeat == 2
    env = make_env("minigrid", "room2")
    obs, _ = env.reset(seed=0)
    assert obs.shape == (3,) and env.step(np.array([0, 0, 1], np.float32))[0].shape == (3,)


def test_plugins_load_lazily_and_dm_control_is_not_imported():
    code = ("import sys, drago.envs, drago.envs.registry as r; a = r._registry.plugins_loaded; "
            "drago.envs.make_env('minigrid', 'room1'); drago.envs.env_spec('pendulum'); "
            "print(a, r._registry.plugins_loaded, 'dm_control' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert out.stdout.split() == ["False", "True", "False"], out.stderr


# ---- your own domain from gymnasium envs ------------------------------------------------------------
def test_a_discrete_gymnasium_env_takes_one_hot_actions(registered):
    domain = registered(gym_domain("cartpole", {"balance": "CartPole-v1"}, episode_length=50))
    assert "cartpole" in available_domains() and is_domain("cartpole")
    assert env_spec("cartpole") == EnvSpec("cartpole", 4, 2, True)
    assert domain.env_spec() is env_spec("cartpole")  # read once, cached
    env = make_env("cartpole", "balance")
    assert env.action_space.shape == (2,) and env.native_action(np.array([0.1, 0.9])) == 1
    obs, _ = env.reset(seed=0)
    assert obs.dtype == np.float32 and obs.shape == (4,)
    right = env.step(np.array([0.0, 1.0], np.float32))[0]
    env.reset(seed=0)
    left = env.step(np.array([1.0, 0.0], np.float32))[0]
    assert right[1] > obs[1] > left[1]  # cart velocity follows the one-hot's argmax
    # The trainer plays fixed-length episodes: after the pole falls the env absorbs.
    env.reset(seed=0)
    steps = [env.step(np.array([0.0, 1.0], np.float32)) for _ in range(60)]
    end = next(i for i, s in enumerate(steps) if s[2])
    assert all(s[2] and s[1] == 0.0 for s in steps[end + 1:])
    np.testing.assert_array_equal(steps[end][0], steps[-1][0])
    assert sum(s[1] for s in steps) == end + 1


def test_a_box_gymnasium_env_takes_actions_in_minus_one_one(registered):
    keep_low = reward_variant("Pendulum-v1", pendulum_keep_low_reward)
    registered(gym_domain("swing", {"up": "Pendulum-v1", "low": keep_low}, episode_length=200, optimum={"up": 0.0},
                          sequences={"both": ("up", "low")}))
    assert env_spec("swing") == EnvSpec("swing", 3, 1, False)
    assert task_optimum("swing", "up") == 0.0 and task_optimum("swing", "low") is None
    env = make_env("swing", "up", max_episode_steps=3)
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    np.testing.assert_allclose(env.native_action([1.0]), [2.0])  # Pendulum's torque bound is 2
    np.testing.assert_allclose(env.native_action([-5.0]), [-2.0])  # clipped first
    first, _ = env.reset(seed=7)
    raw = gym.make("Pendulum-v1").unwrapped
    raw.reset(seed=0)
    raw.state = env.env.unwrapped.state.copy()
    obs, reward, terminated, truncated, _ = env.step(np.array([0.5], np.float32))
    raw_obs, raw_reward, *_ = raw.step(np.array([1.0], np.float32))
    np.testing.assert_allclose(obs, raw_obs.astype(np.float32))
    assert reward == pytest.approx(raw_reward) and not terminated and not truncated
    assert [env.step([0.0])[3] for _ in range(3)] == [False, True, True]
    # reset(seed) replays; the keep-low task has the same dynamics and its own reward
    np.testing.assert_array_equal(env.reset(seed=7)[0], first)
    low = make_env("swing", "low")
    np.testing.assert_array_equal(low.reset(seed=7)[0], first)
    obs, reward, *_ = low.step([0.5])
    assert reward == pytest.approx((1 - obs[0]) / 2, abs=1e-6)


def test_action_repeat_sums_rewards_and_seeds_replay(registered):
    registered(gym_domain("pend2", {"up": "Pendulum-v1"}, episode_length=100, action_repeat=2))
    many, one = make_env("pend2", "up"), make_env("pend2", "up", action_repeat=1)
    assert many.action_repeat == 2 and one.action_repeat == 1
    np.testing.assert_array_equal(many.reset(seed=3)[0], one.reset(seed=3)[0])
    for action in ([0.3], [-1.0], [1.0]):
        obs, reward, *_ = many.step(action)
        steps = [one.step(action) for _ in range(2)]
        assert reward == pytest.approx(sum(s[1] for s in steps))
        np.testing.assert_array_equal(obs, steps[-1][0])
    env = make_env("pend2", "up")
    first = [env.reset(seed=5)[0] for _ in range(2)]
    assert np.array_equal(first[0], first[1]) and not np.array_equal(env.reset()[0], first[0])


def test_builtin_pendulum_is_a_reward_family_on_fixed_dynamics():
    assert available_tasks("pendulum") == ["pendulum-swingup", "pendulum-keep-low", "pendulum-spin"]
    assert get_domain("pendulum").sequences["pendulum"] == ("pendulum-keep-low", "pendulum-spin", "pendulum-swingup")
    envs = [make_env("pendulum", task) for task in available_tasks("pendulum")]
    starts = [env.reset(seed=1)[0] for env in envs]
    steps = [env.step([1.0]) for env in envs]
    for start, step in zip(starts[1:], steps[1:]):
        np.testing.assert_array_equal(start, starts[0])
        np.testing.assert_array_equal(step[0], steps[0][0])  # same dynamics
    obs = steps[0][0]
    assert steps[1][1] == pytest.approx((1 - obs[0]) / 2, abs=1e-6)
    assert steps[2][1] == pytest.approx(min(abs(obs[2]) / 8, 1), abs=1e-6)
    assert steps[0][1] < 0  # the stock swing-up cost


# ---- one-line errors ---------------------------------------------------------------------------------
class DictObsEnv(gym.Env):
    observation_space = gym.spaces.Dict({"x": gym.spaces.Box(-1, 1, (2,))})
    action_space = gym.spaces.Discrete(2)


def test_registration_errors_are_one_line(registered):
    registered(gym_domain("mine", {"a": "CartPole-v1"}, episode_length=10))
    with pytest.raises(DomainError) as err:
        register_domain(gym_domain("mine", {"b": "CartPole-v1"}, episode_length=10))
    assert "domain 'mine' is already registered (register_domain); choose another name or pass replace=True" \
        == one_line_error(err)
    with pytest.raises(DomainError, match="'minigrid' is already registered \\(built-in\\)"):
        register_domain(gym_domain("minigrid", {"a": "CartPole-v1"}, episode_length=10))
    registered(gym_domain("mine", {"b": "CartPole-v1"}, episode_length=10), replace=True)
    assert available_tasks("mine") == ["b"]
    with pytest.raises(DomainError) as err:
        register_domain("CartPole-v1")
    assert "register_domain takes a drago.envs.Domain, got str" in one_line_error(err)
    for bad, says in (("dmc:mine", "the prefix dmc: is reserved for its family"), ("-x", "bad domain name '-x'")):
        with pytest.raises(DomainError) as err:
            register_domain(gym_domain(bad, {"a": "CartPole-v1"}, episode_length=10))
        assert says in one_line_error(err)
    with pytest.raises(DomainError) as err:
        gym_domain("my domain", {"a": "CartPole-v1"}, episode_length=10)
    assert "a domain needs a non-empty name without spaces" in one_line_error(err)
    with pytest.raises(DomainError) as err:
        Domain(name="d", spec=EnvSpec("e", 1, 1, False), tasks={"t": ""}, make=lambda *a, **k: None, episode_length=1)
    assert "EnvSpec('d', obs_dim, action_dim, discrete)" in one_line_error(err)
    with pytest.raises(DomainError) as err:
        gym_domain("d", {"t": "CartPole-v1"}, episode_length=5, sequences={"s": ("t", "u")})
    assert "sequence 's' names unknown tasks ['u']" in one_line_error(err)


@pytest.mark.parametrize("source,says", [
    (DictObsEnv, "observation space Dict('x': Box(-1.0, 1.0, (2,), float32)) and action space Discrete(2)"),
    ("FrozenLake-v1", "env 'FrozenLake-v1' has observation space Discrete(16) and action space Discrete(4)"),
    ("NoSuchEnv-v0", "cannot make env 'NoSuchEnv-v0': NameNotFound"),
])
def test_unsupported_spaces_name_the_env_and_its_spaces(registered, source, says):
    registered(gym_domain("odd", {"t": source}, episode_length=10))
    with pytest.raises(DomainError) as err:
        env_spec("odd")
    message = one_line_error(err)
    assert message.startswith("domain 'odd', task 't': ") and says in message
    assert "Box or Discrete action space" in message or "NameNotFound" in message


def test_lookup_errors_are_one_line(registered):
    with pytest.raises(DomainError) as err:
        env_spec("nope")
    assert one_line_error(err).startswith("unknown domain 'nope'; valid domains: minigrid, cheetah, walker, pendulum")
    with pytest.raises(DomainError) as err:
        make_env("walker", "cheetah-run")
    assert one_line_error(err) == ("unknown task 'cheetah-run' for domain walker; valid tasks: walker-stand, "
                                   "walker-walk, walker-run, walker-walk-backwards, walker-run-backwards")
    with pytest.raises(DomainError) as err:
        task_optimum("minigrid", "room9")
    assert "unknown task 'room9' for domain minigrid" in one_line_error(err)
    with pytest.raises(DomainError) as err:
        make_env("pendulum", "pendulum-spin", dense_reward=True)
    assert one_line_error(err) == "dense_reward applies to the grid only, not to domain pendulum"
    registered(gym_domain("mixed", {"cart": "CartPole-v1", "pend": "Pendulum-v1"}, episode_length=10))
    make_env("mixed", "cart")
    with pytest.raises(DomainError) as err:
        make_env("mixed", "pend")
    assert "a domain's tasks must share their sizes" in one_line_error(err)
    assert is_domain("gym:CartPole-v1") and not is_domain("gym:NoSuchEnv-v0") and not is_domain("nope")
    assert env_spec("gym:CartPole-v1") == EnvSpec("gym:CartPole-v1", 4, 2, True)
    with pytest.raises(DomainError) as err:
        env_spec("gym:NoSuchEnv-v0")
    assert one_line_error(err).startswith("unknown domain 'gym:NoSuchEnv-v0': gym: takes a registered gymnasium id")


# ---- plug-ins through entry points -------------------------------------------------------------------
PLUGIN_MODULE = '''
from drago.envs import EnvSpec, gym_domain

DOMAIN = gym_domain("plug-cart", {"balance": "CartPole-v1"}, episode_length=20)
CLASH = gym_domain("minigrid", {"balance": "CartPole-v1"}, episode_length=20)
NOT_A_DOMAIN = 42


def make_domain():
    return gym_domain("plug-pend", {"swing": "Pendulum-v1"}, episode_length=20)
'''

SELF_REGISTERING_MODULE = '''
from drago.envs import gym_domain, register_domain

register_domain(gym_domain("plug-self", {"balance": "CartPole-v1"}, episode_length=20))
'''

ENTRY_POINTS = '''
[drago.domains]
good = drago_fake_plugin:DOMAIN
factory = drago_fake_plugin:make_domain
selfreg = drago_fake_selfreg
broken = drago_fake_broken:DOMAIN
number = drago_fake_plugin:NOT_A_DOMAIN
clash = drago_fake_plugin:CLASH
'''


@pytest.fixture
def fake_distribution(tmp_path, monkeypatch):
    """A package 'drago-fake-domains' installed as a dist-info folder on sys.path, with six entry points."""
    (tmp_path / "drago_fake_plugin.py").write_text(PLUGIN_MODULE)
    (tmp_path / "drago_fake_selfreg.py").write_text(SELF_REGISTERING_MODULE)
    (tmp_path / "drago_fake_broken.py").write_text("raise RuntimeError('the plug-in is broken\\non two lines')\n")
    info = tmp_path / "drago_fake_domains-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: drago-fake-domains\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(ENTRY_POINTS))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield
    monkeypatch.undo()
    for name in ("drago_fake_plugin", "drago_fake_selfreg", "drago_fake_broken"):
        sys.modules.pop(name, None)
    load_plugins(reload=True)  # forget the fake plug-ins
    assert not any(name.startswith("plug-") for name in available_domains())


def test_entry_point_plugins_are_discovered_and_failures_are_one_warning_line(fake_distribution, capsys):
    problems = load_plugins(reload=True)
    warnings = capsys.readouterr().err.strip().splitlines()
    assert len(warnings) == 3 and len(problems) == 3
    by_entry = {p.entry_point.split(" = ")[0]: p for p in problems}
    assert set(by_entry) == {"broken", "number", "clash"}
    assert all(p.package == "drago-fake-domains" for p in problems)
    assert warnings[0] == ("drago: warning: domain plug-in 'broken = drago_fake_broken:DOMAIN' of package "
                           "'drago-fake-domains' skipped: RuntimeError: the plug-in is broken on two lines")
    assert {p.kind for p in problems} == {"domain"}
    assert "it loads a int, not a drago.envs.Domain" in str(by_entry["number"])
    assert "domain 'minigrid' is already registered (built-in)" in str(by_entry["clash"])
    assert plugin_problems() == problems
    for name in ("plug-cart", "plug-pend", "plug-self"):
        assert name in available_domains()
    assert "entry point 'good = drago_fake_plugin:DOMAIN' of package 'drago-fake-domains'" in \
        str(pytest.raises(DomainError, register_domain, get_domain("plug-cart")).value)
    env = make_env("plug-pend", "swing")
    env.reset(seed=0)
    assert env.step([0.0])[0].shape == (3,)
    assert env_spec("minigrid") == EnvSpec("minigrid", 3, 3, True)  # the clash left the built-in alone
    assert make_env("minigrid", "room1").reset(seed=0)[0].shape == (3,)
    assert load_plugins() == problems and capsys.readouterr().err == ""  # loaded once: no second warning


def test_a_monkeypatched_entry_point_list_works_too(monkeypatch, capsys):
    from importlib import metadata

    class FakeEP:
        name, value, dist = "bad", "nowhere:thing", None

        def load(self):
            raise ImportError("No module named 'nowhere'")

    monkeypatch.setattr(metadata, "entry_points", lambda group: [FakeEP()] if group == "drago.domains" else [])
    try:
        problems = load_plugins(reload=True)
        assert [str(p) for p in problems] == [("domain plug-in 'bad = nowhere:thing' of package 'unknown package' "
                                               "skipped: ImportError: No module named 'nowhere'")]
        assert capsys.readouterr().err.count("\n") == 1
        assert env_spec("walker").obs_dim == 24
    finally:
        monkeypatch.undo()
        load_plugins(reload=True)


# ---- every stock dm_control task: dmc: ---------------------------------------------------------------
@needs_dmc
def test_dmc_hopper_stand():
    assert env_spec("dmc:hopper") == EnvSpec("dmc:hopper", 15, 4, False)  # imports drago.envs.dmc: MUJOCO_GL first
    from dm_control import suite

    assert available_tasks("dmc:hopper") == [f"hopper-{t}" for d, t in suite.ALL_TASKS if d == "hopper"]
    assert is_domain("dmc:hopper") and is_domain("dmc:hopper-stand") and is_domain("dmc:quadruped-walk")
    assert not is_domain("dmc:hoper") and not is_domain("dmc:hopper-flip")
    domain = get_domain("dmc:hopper")
    assert (domain.action_repeat, domain.episode_length, domain.requires) == (2, 500, ("dm_control",))
    a, b = make_env("dmc:hopper", "hopper-stand"), make_env("dmc:hopper-stand", "hopper-stand")
    first = a.reset(seed=4)[0]
    np.testing.assert_array_equal(b.reset(seed=4)[0], first)
    actions = np.random.default_rng(0).uniform(-1, 1, (5, 4))
    obs_a = [a.step(x) for x in actions]
    obs_b = [b.step(x) for x in actions]
    for sa, sb in zip(obs_a, obs_b):
        np.testing.assert_array_equal(sa[0], sb[0])
        assert sa[1] == sb[1] and sa[2] is False and sa[3] is False
    # The first observation is the suite's observation dict flattened in its order, seeded from np_random.
    seed = int(gym.utils.seeding.np_random(4)[0].integers(2**32))
    raw = suite.load("hopper", "stand", task_kwargs={"random": seed, "time_limit": float("inf")})
    want = np.concatenate([np.asarray(v, np.float32).ravel() for v in raw.reset().observation.values()])
    np.testing.assert_array_equal(first, want)
    assert a.observation_space.shape == (15,) and a.action_space.shape == (4,)


@needs_dmc
def test_dmc_errors_and_tasks_of_other_sizes():
    with pytest.raises(DomainError) as err:
        env_spec("dmc:hoper")
    message = one_line_error(err)
    assert message.startswith("unknown domain 'dmc:hoper': dmc: takes a dm_control suite domain")
    assert "hopper" in message
    with pytest.raises(DomainError) as err:
        available_tasks("dmc:hopper-flip")
    assert "dm_control's hopper has no task 'flip'; tasks: stand, hop" in one_line_error(err)
    with pytest.raises(DomainError) as err:
        make_env("dmc:hopper", "walker-run")
    assert one_line_error(err) == ("unknown task 'walker-run' for domain dmc:hopper; valid tasks: hopper-stand, "
                                   "hopper-hop")
    # finger-spin and finger-turn_* differ in size: two domains
    assert available_tasks("dmc:finger") == ["finger-spin"]
    assert available_tasks("dmc:finger-turn_hard") == ["finger-turn_hard", "finger-turn_easy"]
    assert env_spec("dmc:finger-turn_easy").obs_dim == 12 and env_spec("dmc:finger").obs_dim == 9


@needs_dmc
def test_dmc_actions_are_rescaled_to_the_actuator_range():
    env = make_env("dmc:quadruped", "quadruped-walk")
    env.reset(seed=0)
    env.step(np.ones(12))
    spec = env._env.action_spec()
    np.testing.assert_allclose(env.physics.data.ctrl, spec.maximum)
    env.step(-np.ones(12) * 3)
    np.testing.assert_allclose(env.physics.data.ctrl, spec.minimum)


@needs_dmc
def test_a_dm_control_termination_becomes_an_absorbing_state():
    import dm_env

    env = make_env("dmc:hopper", "hopper-hop", action_repeat=3)
    env.reset(seed=0)
    inner_step, calls = env._env.step, []

    def step(action):  # a task that ends at its 4th control step, as LQR's does once it has converged
        calls.append(1)
        time_step = inner_step(action)
        return time_step._replace(step_type=dm_env.StepType.LAST) if len(calls) == 4 else time_step

    env._env.step = step
    assert env.step(np.zeros(4))[2] is False
    obs, _, terminated, _, _ = env.step(np.zeros(4))  # ends after one of its three control steps
    assert terminated and len(calls) == 4
    for _ in range(3):
        again, reward, terminated, _, _ = env.step(np.ones(4))
        np.testing.assert_array_equal(again, obs)
        assert reward == 0.0 and terminated and len(calls) == 4
    env._env.step = inner_step
    assert env.reset(seed=0)[0].shape == (15,) and env.step(np.zeros(4))[2] is False
