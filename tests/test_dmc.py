"""DeepMind Control cheetah and walker (paper Appendix C): rewards in closed form, sizes, action repeat,
seeding, external episode length, the catalogue, a smoke training run and headless GIF recording."""

from __future__ import annotations

import importlib.util
import json
import math
import os

import numpy as np
import pytest

if importlib.util.find_spec("dm_control") is None:  # pragma: no cover - depends on the installation
    if os.environ.get("CI"):
        raise ImportError("dm_control is missing on CI: scripts/setup.sh must install the dmc extra")
    pytest.skip("dm_control is not installed (pip install -e '.[dmc]'; scripts/setup.sh installs it)",
                allow_module_level=True)

# drago.envs.dmc first: it chooses a headless MUJOCO_GL before dm_control is imported.
from drago.envs.dmc import DMCEnv, reward_function  # noqa: E402, I001

from dm_control.suite import cheetah as stock_cheetah  # noqa: E402, I001
from dm_control.suite import walker as stock_walker  # noqa: E402

from drago import cli  # noqa: E402
from drago.config import ConfigError, load_config  # noqa: E402
from drago.envs import (DMC_SEQUENCES, DMC_TASKS, DMC_TRANSFER_TASKS, available_tasks, env_spec,  # noqa: E402
                        make_env)
from drago.envs.video import record_episode, save_video  # noqa: E402
from drago.seeding import rng_state, set_rng_state  # noqa: E402

CHEETAH_TASKS = ["cheetah-run", "cheetah-jump", "cheetah-run-backwards", "cheetah-jump-and-run",
                 "cheetah-jump-and-run-backwards"]
WALKER_TASKS = ["walker-stand", "walker-walk", "walker-run", "walker-walk-backwards", "walker-run-backwards"]


# ---- the paper's formulas (Appendix C), written independently of drago.envs.dmc ----------------------
def tol(x: float, lo: float, hi: float, margin: float, sigmoid: str = "gaussian", v: float = 0.1) -> float:
    if lo <= x <= hi:
        return 1.0
    delta = (lo - x if x < lo else x - hi) / margin
    if sigmoid == "gaussian":
        return math.exp(-0.5 * (delta * math.sqrt(-2 * math.log(v))) ** 2)
    return 1 - delta * (1 - v) if delta * (1 - v) < 1 else 0.0


def clip01(x: float) -> float:
    return min(max(x, 0.0), 1.0)


def expected_reward(task: str, vx: float, z: dict[str, float], up: float) -> float:
    inf = math.inf
    if task == "cheetah-run":
        return clip01(vx / 10)
    if task == "cheetah-run-backwards":
        return clip01(-vx / 8)
    if task == "cheetah-jump":
        s = tol(vx, -0.5, 0.5, 0.5, "linear", 0.0)
        stand = [(5 * tol((z["torso"] + z[f]) / 2, 1.2, inf, 0.6) + s) / 6 for f in ("bfoot", "ffoot")]
        return sum(stand) / 2
    if task.startswith("cheetah-jump-and-run"):
        jump = sum(tol((z["torso"] + z[f]) / 2, 0.9, inf, 0.45) for f in ("ffoot", "bfoot")) / 2
        run = clip01((-vx if task.endswith("backwards") else vx) / 7.5)
        return (jump + run) / 2
    stand = (3 * tol(z["torso"], 1.2, inf, 0.6) + (1 + up) / 2) / 4
    speed = {"stand": 0, "walk": 1, "run": 8}[task.split("-")[1]]
    if speed == 0:
        return stand
    move = clip01((-vx if task.endswith("backwards") else vx) / speed)
    return stand * (5 * move + 1) / 6


def set_state(env: DMCEnv, qpos: dict[str, float], vx: float) -> None:
    """Set joint positions by name, a pure x-translation velocity vx, and recompute the derived fields."""
    physics = env.physics
    with physics.reset_context():
        physics.data.qpos[:] = 0
        physics.data.qvel[:] = 0
        for name, value in qpos.items():
            physics.named.data.qpos[name] = value
        physics.named.data.qvel["rootx"] = vx
    physics.forward()


def read(physics, bodies) -> tuple[float, dict[str, float], float]:
    vx = float(physics.named.data.sensordata["torso_subtreelinvel"][0])
    z = {b: float(physics.named.data.xpos[b, "z"]) for b in bodies}
    return vx, z, float(physics.named.data.xmat["torso", "zz"])


def cheetah_states(env: DMCEnv, rng: np.random.Generator):
    lo, hi = env.physics.model.jnt_range[3:].T
    joints = env.physics.named.data.qpos.axes.row.names[3:]
    for rootz in (-0.3, 0.0, 0.3, 0.6, 1.0, 1.6):
        for vx in (-12.0, -8.0, -7.5, -4.0, -0.7, -0.25, 0.0, 0.4, 0.75, 3.75, 7.5, 9.0, 12.0):
            angles = dict(zip(joints, rng.uniform(lo, hi)))
            yield {"rootz": rootz, "rooty": float(rng.uniform(-0.6, 0.6)), **angles}, vx


def walker_states(env: DMCEnv, rng: np.random.Generator):
    lo, hi = env.physics.model.jnt_range[3:].T
    joints = env.physics.named.data.qpos.axes.row.names[3:]
    for rootz in (-1.0, -0.6, -0.3, -0.1, 0.0, 0.4):
        for vx in (-10.0, -8.0, -4.0, -1.0, -0.5, 0.0, 0.5, 1.0, 4.0, 8.0, 10.0):
            angles = dict(zip(joints, rng.uniform(lo, hi)))
            yield {"rootz": rootz, "rooty": float(rng.uniform(-math.pi, math.pi)), **angles}, vx


# ---- rewards -------------------------------------------------------------------------------------
@pytest.mark.parametrize("task", CHEETAH_TASKS + WALKER_TASKS)
def test_reward_equals_the_closed_form_on_hand_set_states(task):
    env = DMCEnv(task)
    domain = task.split("-")[0]
    states = cheetah_states if domain == "cheetah" else walker_states
    bodies = ("torso", "bfoot", "ffoot") if domain == "cheetah" else ("torso",)
    reward = reward_function(task)
    values = []
    for qpos, vx in states(env, np.random.default_rng(0)):
        set_state(env, qpos, vx)
        sensed_vx, z, up = read(env.physics, bodies)
        assert sensed_vx == pytest.approx(vx, abs=1e-9)  # vx is the subtree's centre-of-mass velocity
        want = expected_reward(task, vx, z, up)
        assert reward(env.physics) == pytest.approx(want, abs=1e-9), (qpos, vx)
        assert env._env.task.get_reward(env.physics) == pytest.approx(want, abs=1e-9)  # what step() returns
        values.append(want)
    # The states reach both ends of every reward and values in between.
    assert min(values) < 0.2 and max(values) > 0.8 and any(0.3 < v < 0.7 for v in values), task


@pytest.mark.parametrize("task,stock", [
    ("cheetah-run", lambda: stock_cheetah.Cheetah(random=0)),
    ("walker-stand", lambda: stock_walker.PlanarWalker(move_speed=0, random=0)),
    ("walker-walk", lambda: stock_walker.PlanarWalker(move_speed=1, random=0)),
    ("walker-run", lambda: stock_walker.PlanarWalker(move_speed=8, random=0)),
])
def test_stock_tasks_match_dm_control(task, stock):
    env, stock_task = DMCEnv(task), stock()
    states = cheetah_states if task.startswith("cheetah") else walker_states
    for qpos, vx in states(env, np.random.default_rng(1)):
        set_state(env, qpos, vx)
        assert reward_function(task)(env.physics) == pytest.approx(stock_task.get_reward(env.physics), abs=1e-12)


def test_cheetah_jump_and_run_thresholds_are_three_quarters_of_jump_and_run():
    env = DMCEnv("cheetah-jump-and-run")
    physics = env.physics
    set_state(env, {}, 0.0)
    _, z, _ = read(physics, ("torso", "bfoot", "ffoot"))
    offsets = [z[f] - z["torso"] for f in ("bfoot", "ffoot")]
    # Torso height such that both (z_torso + z_foot) / 2 lie in [0.9, 1.2): full jump-and-run height
    # term, but below the jump task's 1.2.
    torso = 0.95 - min(offsets) / 2
    for vx, run_term in ((7.5, 1.0), (3.75, 0.5), (-3.75, 0.0), (10.0, 1.0)):
        set_state(env, {"rootz": torso - z["torso"]}, vx)
        _, zz, _ = read(physics, ("torso", "bfoot", "ffoot"))
        heights = [(zz["torso"] + zz[f]) / 2 for f in ("bfoot", "ffoot")]
        assert all(0.9 <= h < 1.2 for h in heights)
        assert reward_function("cheetah-jump-and-run")(physics) == pytest.approx((1.0 + run_term) / 2, abs=1e-12)
        assert reward_function("cheetah-jump-and-run-backwards")(physics) == pytest.approx(
            (1.0 + clip01(-vx / 7.5)) / 2, abs=1e-12)
        assert reward_function("cheetah-jump")(physics) < 1.0
    # At the margin (0.45 below 0.9) the gaussian term is 0.1.
    set_state(env, {"rootz": (0.45 - min(offsets) / 2) - z["torso"]}, 0.0)
    _, zz, _ = read(physics, ("torso", "bfoot", "ffoot"))
    heights = sorted((zz["torso"] + zz[f]) / 2 for f in ("bfoot", "ffoot"))
    assert heights[0] == pytest.approx(0.45, abs=1e-9)
    other = tol(heights[1], 0.9, math.inf, 0.45)
    assert reward_function("cheetah-jump-and-run")(physics) == pytest.approx((0.1 + other) / 2 / 2, abs=1e-9)


def test_walker_move_term_is_clip_vx_over_speed():
    env = DMCEnv("walker-walk")
    set_state(env, {"rootz": 0.0}, 0.0)  # standing height 1.3, upright: stand = 1
    assert reward_function("walker-stand")(env.physics) == pytest.approx(1.0)
    for task, speed, sign in (("walker-walk", 1, 1), ("walker-run", 8, 1), ("walker-walk-backwards", 1, -1),
                              ("walker-run-backwards", 8, -1)):
        for vx in np.linspace(-10, 10, 41):
            set_state(env, {"rootz": 0.0}, float(vx))
            move = clip01(sign * vx / speed)
            assert reward_function(task)(env.physics) == pytest.approx((5 * move + 1) / 6, abs=1e-12)


# ---- the wrapper -----------------------------------------------------------------------------------
@pytest.mark.parametrize("domain,obs_dim", [("cheetah", 17), ("walker", 24)])
def test_sizes_and_observation_order(domain, obs_dim):
    spec = env_spec(domain)
    assert (spec.obs_dim, spec.action_dim, spec.discrete) == (obs_dim, 6, False)
    for task in available_tasks(domain):
        env = make_env(domain, task)
        assert env.observation_space.shape == (obs_dim,) and env.action_space.shape == (6,)
        assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
        obs, _ = env.reset(seed=0)
        for _ in range(2):
            assert obs.dtype == np.float32 and obs.shape == (obs_dim,)
            p = env.physics.named.data
            if domain == "cheetah":  # position = qpos[1:], velocity = qvel
                want = np.concatenate([p.qpos[1:], p.qvel])
            else:  # orientations (xx, xz of 7 bodies), torso height, velocity
                want = np.concatenate([p.xmat[1:, ["xx", "xz"]].ravel(), [p.xpos["torso", "z"]], p.qvel])
            np.testing.assert_array_equal(obs, want.astype(np.float32))
            obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            assert isinstance(reward, float) and terminated is False and truncated is False


def test_official_action_repeats_and_frame_rates():
    assert make_env("cheetah", "cheetah-run").action_repeat == 4
    assert make_env("walker", "walker-run").action_repeat == 2
    assert make_env("cheetah", "cheetah-run").metadata["render_fps"] == pytest.approx(25)
    assert make_env("walker", "walker-run").metadata["render_fps"] == pytest.approx(20)
    assert DMCEnv("walker-run").physics.timestep() == pytest.approx(0.0025)
    assert DMCEnv("walker-run")._env.control_timestep() == pytest.approx(0.025)
    assert DMCEnv("cheetah-run")._env.control_timestep() == pytest.approx(0.01)


@pytest.mark.parametrize("task,repeat", [("cheetah-jump", 4), ("walker-walk", 2), ("walker-run-backwards", 3)])
def test_action_repeat_sums_the_rewards_of_the_repeated_steps(task, repeat):
    many, one = DMCEnv(task, action_repeat=repeat), DMCEnv(task, action_repeat=1)
    obs_many, _ = many.reset(seed=5)
    obs_one, _ = one.reset(seed=5)
    np.testing.assert_array_equal(obs_many, obs_one)
    rng = np.random.default_rng(0)
    total = 0.0
    for _ in range(20):
        action = rng.uniform(-1, 1, 6)
        obs_many, reward, *_ = many.step(action)
        steps = [one.step(action) for _ in range(repeat)]
        obs_one = steps[-1][0]
        assert reward == pytest.approx(sum(step[1] for step in steps), abs=1e-12)
        np.testing.assert_array_equal(obs_many, obs_one)
        total += reward
    assert total > 0


def test_actions_are_clipped_to_the_actuator_range():
    a, b = DMCEnv("cheetah-run"), DMCEnv("cheetah-run")
    a.reset(seed=1)
    b.reset(seed=1)
    big = np.array([5.0, -3.0, 0.5, 2.0, -9.0, 0.0])
    np.testing.assert_array_equal(a.step(big)[0], b.step(np.clip(big, -1, 1))[0])


@pytest.mark.parametrize("task", ["cheetah-run", "walker-walk"])
def test_seeded_resets_are_reproducible(task):
    env = DMCEnv(task)
    first = env.reset(seed=3)[0]
    following = [env.reset()[0] for _ in range(3)]
    assert not np.array_equal(following[0], following[1])  # each reset draws a new initial state
    np.testing.assert_array_equal(env.reset(seed=3)[0], first)  # reset(seed) restarts the sequence
    np.testing.assert_array_equal(np.stack([env.reset()[0] for _ in range(3)]), np.stack(following))
    assert not np.array_equal(DMCEnv(task).reset(seed=4)[0], first)
    np.testing.assert_array_equal(DMCEnv(task).reset(seed=3)[0], first)  # a new instance too


def test_restoring_np_random_replays_the_next_initial_states():
    """What a resumed run does: the env's generator state alone determines the coming resets."""
    env = DMCEnv("walker-run")
    env.reset(seed=11)
    env.reset()
    saved = rng_state(env.np_random)
    expected = [env.reset()[0] for _ in range(2)]
    other = DMCEnv("walker-run")
    other.reset(seed=999)
    for _ in range(5):
        other.step(np.ones(6))
    set_rng_state(other.np_random, saved)
    np.testing.assert_array_equal(np.stack([other.reset()[0] for _ in range(2)]), np.stack(expected))


def test_episode_length_is_managed_outside_dm_control():
    # The stock cheetah time limit is 10 s = 250 agent steps at repeat 4: go well past it.
    env = DMCEnv("cheetah-run")
    env.reset(seed=0)
    for _ in range(300):
        _, _, terminated, truncated, _ = env.step(np.zeros(6))
        assert not terminated and not truncated
    assert env.physics.data.time == pytest.approx(12.0)
    # walker: 25 s stock limit = 500 agent steps at repeat 2.
    env = DMCEnv("walker-stand")
    env.reset(seed=0)
    for _ in range(520):
        _, _, terminated, truncated, _ = env.step(np.zeros(6))
        assert not terminated and not truncated
    assert env.physics.data.time == pytest.approx(26.0)
    # max_episode_steps only reports truncation; the caller may keep stepping (pre-rollouts).
    env = make_env("cheetah", "cheetah-jump", max_episode_steps=3)
    env.reset(seed=0)
    assert [env.step(np.zeros(6))[3] for _ in range(5)] == [False, False, True, True, True]
    env.reset()
    assert env.elapsed_steps == 0 and env.step(np.zeros(6))[3] is False


def test_step_before_reset_is_an_error():
    with pytest.raises(RuntimeError, match="reset"):
        DMCEnv("cheetah-run").step(np.zeros(6))


# ---- catalogue, config -----------------------------------------------------------------------------
def test_catalogue_and_sequences():
    assert available_tasks("cheetah") == CHEETAH_TASKS
    assert sorted(available_tasks("walker")) == sorted(WALKER_TASKS)
    assert {n for n, t in DMC_TASKS.items() if t.stock} == {"cheetah-run", "walker-stand", "walker-walk", "walker-run"}
    assert DMC_SEQUENCES == {"cheetah": ("cheetah-run", "cheetah-jump", "cheetah-run-backwards"),
                             "walker": ("walker-run", "walker-walk", "walker-walk-backwards", "walker-stand")}
    for task in DMC_TASKS.values():
        assert task.reward  # a closed form for `drago list`
    assert DMC_TASKS["walker-run-backwards"].reward.startswith("stand * (5 clip(-vx/8, 0, 1) + 1) / 6")


def test_transfer_catalogue_matches_table_1():
    table = {t.name: (t.domain, t.target, t.pre_rollout_source, t.stage, t.pre_rollout_stage)
             for t in DMC_TRANSFER_TASKS.values()}
    assert table == {
        "jump2run": ("cheetah", "cheetah-run", "cheetah-jump", 2, 2),
        "jump2back": ("cheetah", "cheetah-run-backwards", "cheetah-jump", 3, 2),
        "jump-and-run": ("cheetah", "cheetah-jump-and-run", None, 2, None),
        "jump-and-back": ("cheetah", "cheetah-jump-and-run-backwards", None, 3, None),
        "walk2run": ("walker", "walker-run", "walker-walk", 2, 2),
        "run2back": ("walker", "walker-run-backwards", "walker-run", 3, 1),
        "back2run": ("walker", "walker-run", "walker-walk-backwards", 3, 3),
        "stand2run": ("walker", "walker-run", "walker-stand", 4, 4),
    }
    assert all(t.pre_rollout_steps == 100 for t in DMC_TRANSFER_TASKS.values())
    assert [t.after_inferred for t in DMC_TRANSFER_TASKS.values()] == [False, True, False, True, True, True, True, True]


@pytest.mark.parametrize("preset,tasks,repeat,length,horizon", [
    ("cheetah", DMC_SEQUENCES["cheetah"], 4, 250, 25), ("walker", DMC_SEQUENCES["walker"], 2, 500, 15),
    ("cheetah-cpu", DMC_SEQUENCES["cheetah"], 4, 250, 5), ("walker-cpu", DMC_SEQUENCES["walker"], 2, 500, 5),
])
def test_presets(preset, tasks, repeat, length, horizon):
    cfg = load_config(preset)
    assert (cfg.env.tasks, cfg.env.action_repeat, cfg.env.episode_length, cfg.agent.tdmpc.horizon) == (
        tasks, repeat, length, horizon)
    assert (cfg.agent.tdmpc.first_step_qr_only, cfg.agent.tdmpc.use_crelu, cfg.agent.tdmpc.update_freq) == (True, False, 2)
    assert (cfg.method.vae.kl_coef, cfg.method.rehearsal.freq) == (0.02, 10)
    if not preset.endswith("-cpu"):
        assert (cfg.agent.tdmpc.mlp_dim, cfg.agent.batch_size, cfg.agent.tdmpc.num_samples, cfg.method.vae.hidden_dim) == (
            512, 512, 512, 256)
        assert (cfg.train.eval_freq, cfg.train.eval_episodes) == (20000, 20)
        assert cfg.train.steps_per_task == {"cheetah": 500_000, "walker": 300_000}[preset]


@pytest.mark.parametrize("overrides,message", [
    (["env.domain=cheetah"], "unknown task 'room1' for domain cheetah; valid tasks: cheetah-run"),
    (["env.tasks=[walker-run]"], "unknown task 'walker-run' for domain minigrid"),
    (["env.domain=walker", "env.tasks=[walker-run]", "env.dense_reward=true"], "applies to the grid only"),
    (["env.action_repeat=2"], "must be 1 for the grid and other tabular domains"),
])
def test_config_errors_name_the_problem(overrides, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        load_config("smoke", overrides)


def test_make_env_rejects_unknown_tasks_and_grid_options():
    with pytest.raises(ValueError, match="valid tasks: walker-stand"):
        make_env("walker", "cheetah-run")
    with pytest.raises(ValueError, match="grid only"):
        make_env("cheetah", "cheetah-run", dense_reward=True)


# ---- end to end ------------------------------------------------------------------------------------
SMOKE_CHEETAH = ["env.domain=cheetah", "env.tasks=[cheetah-run,cheetah-jump]", "env.action_repeat=4",
                 "env.episode_length=20", "train.steps_per_task=80", "agent.seed_steps=20", "agent.batch_size=16",
                 "train.eval_freq=160", "train.checkpoint_freq=80", "train.updates_per_episode=5"]


@pytest.mark.slow
@pytest.mark.parametrize("method", ["continual", "drago"])
def test_smoke_training_run_on_cheetah(tmp_path, method):
    """Two tasks of four 20-step episodes; DRAGO's reviewer plans and updates in task 2."""
    out = tmp_path / "run"
    assert cli.main(["train", "smoke", "--method", method, "--out", str(out), "--no-progress",
                     "train.tensorboard=false", *SMOKE_CHEETAH]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and summary["domain"] == "cheetah"
    assert [t["name"] for t in summary["tasks"]] == ["cheetah-run", "cheetah-jump"]
    assert all(t["env_steps"] == 4 * t["steps"] == 320 for t in summary["tasks"])
    assert (out / "checkpoints" / "task2_cheetah-jump.pt").is_file()
    last = (out / "train.csv").read_text().splitlines()
    header, row = last[0].split(","), last[-1].split(",")
    assert row[header.index("task")] == "cheetah-jump"
    if method == "drago":
        assert row[header.index("reviewer_total_loss")] not in ("", "nan")


# ---- video -----------------------------------------------------------------------------------------
def test_record_episode_to_gif_headless(tmp_path):
    from PIL import Image

    env = make_env("cheetah", "cheetah-run", render_mode="rgb_array")
    env.render_size = (48, 64)
    env.reset(seed=0)
    try:
        frame = env.render()
    except Exception as err:  # noqa: BLE001 - any GL failure means no backend here
        pytest.skip(f"no headless OpenGL backend works here (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {err}")
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8 and frame.std() > 0
    rng = np.random.default_rng(0)
    recording = record_episode(env, 5, lambda obs, t: rng.uniform(-1, 1, 6), tmp_path / "ep.gif", seed=0)
    env.close()
    assert recording.frames == 6 and recording.path.is_file()
    with Image.open(recording.path) as gif:
        assert gif.n_frames == 6 and gif.size == (64, 48)
        assert gif.info["duration"] == 40  # 25 fps: one frame per agent step of 0.04 s


def test_save_video_formats(tmp_path):
    frames = [np.full((8, 8, 3), i * 40, np.uint8) for i in range(3)]
    with pytest.raises(ValueError, match=".gif or .mp4"):
        save_video(frames, tmp_path / "x.avi", 10)
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        with pytest.raises(RuntimeError, match="imageio-ffmpeg"):
            save_video(frames, tmp_path / "x.mp4", 10)
    assert save_video(frames, tmp_path / "x.gif", 10).is_file()
