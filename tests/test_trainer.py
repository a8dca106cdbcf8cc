"""End-to-end behaviour of the continual trainer on the `smoke` preset (paper §3.3, Algorithm 1; docs: Design, how a
run flows).

One smoke run (four tasks of 400 agent steps) takes a few seconds; the module shares one reference run.
"""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from drago import cli
from drago.agent.networks import WorldModel
from drago.agent.speed import resolve_speed
from drago.config import Config, load_config
from drago.continual import METHODS
from drago.continual.naive import Continual, Scratch
from drago.training.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from drago.training.resources import keep_freed_memory
from helpers import ONE_THREAD_ENV, QUIET, SimulatedCrash, crash_at_gradient_step, read_csv, sigkill_in_task_two

TASKS = ("room1", "room2", "room3", "room4")
DRAGO = Path(sys.executable).parent / "drago"


def train(out: Path, *extra: str) -> int:
    return cli.main(["train", "smoke", "--out", str(out), *QUIET, *extra])


@pytest.fixture(scope="module")
def reference(smoke_runs) -> Path:
    """A complete smoke run with seed 1 (the preset's), uninterrupted."""
    return smoke_runs("continual")


def task_checkpoints(run: Path) -> list[Path]:
    return [run / "checkpoints" / f"task{i + 1}_{name}.pt" for i, name in enumerate(TASKS)]


def all_keys(value, prefix="") -> list[str]:
    if isinstance(value, dict):
        out = []
        for k, v in value.items():
            out.append(f"{prefix}{k}")
            out.extend(all_keys(v, f"{prefix}{k}."))
        return out
    return []


def assert_same_state(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def differs(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return any(not torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------------------------------------------
# Outputs of a complete run
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_smoke_run_writes_every_output(reference):
    for name in ("config.yaml", "train.csv", "eval.csv", "timing.csv", "console.log", "summary.json",
                 "visitation.csv"):
        assert (reference / name).is_file(), name
    cfg = Config.from_dict(yaml.safe_load((reference / "config.yaml").read_text()))
    # The settings asked for, with the speed settings' `auto` resolved for this machine (tests/test_speed.py).
    assert "auto" not in (cfg.agent.tdmpc.precision, cfg.agent.tdmpc.compile)
    assert cfg == resolve_speed(load_config("smoke", ["train.tensorboard=false"]), torch.device("cpu"))[0]

    summary = json.loads((reference / "summary.json").read_text())
    assert summary["complete"] is True
    assert [t["name"] for t in summary["tasks"]] == list(TASKS)
    assert all(t["steps"] == 400 and t["episodes"] == 4 for t in summary["tasks"])
    # The contention-free costs each task reports (what the method cost table is made of).
    assert all(t["cpu_time_s"] > 0 and t["peak_rss_mib"] > 50 for t in summary["tasks"])

    train_rows = read_csv(reference / "train.csv")
    assert [(r["task"], int(r["episode"])) for r in train_rows] == [(t, e) for t in TASKS for e in range(1, 5)]
    # Updates start once the 200-step seed phase is over: the first two episodes of a task log no loss.
    for r in train_rows:
        has_loss = r["learner_total_loss"] != ""
        assert has_loss == (int(r["episode"]) > 2)
    eval_rows = read_csv(reference / "eval.csv")
    # Evaluations at the start, every 200 env steps and at the end of each task.
    assert [(r["task"], int(r["env_step"])) for r in eval_rows] == [(t, s) for t in TASKS for s in (0, 200, 400)]

    ckpt = reference / "checkpoints"
    assert sorted(p.name for p in ckpt.iterdir()) == sorted(p.name for p in task_checkpoints(reference))
    assert not list(ckpt.glob("*.tmp")) and not list(ckpt.glob(".*"))  # no temporary file, no resume.pt left


class Terminal(io.StringIO):
    """A terminal's screen as a string: the progress bar is drawn only where the output is a terminal."""

    def isatty(self) -> bool:
        return True


@pytest.mark.slow
@pytest.mark.parametrize("method", ["continual", "drago"])
def test_the_progress_bar_ends_full_with_separate_budgets(method, tmp_path, monkeypatch):
    """With separate budgets a task without a reviewer (every task of continual, DRAGO's first) ends before
    the largest budget the bar started from; what the terminal shows last is still a full bar."""
    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    out = tmp_path / method
    assert cli.main(["train", "smoke", "--method", method, "--out", str(out), "train.tensorboard=false",
                     "env.tasks=[room1,room2]", "train.reviewer_steps_per_task=200"]) == 0
    steps = sum(t["steps"] for t in json.loads((out / "summary.json").read_text())["tasks"])
    # Each drawing of the bar overwrites the last one on the terminal's line: "drago:  80%|████  | 800/1000 ...".
    drawn = re.findall(r"drago: +(\d+)%\|[^|]*\| (\d+)/(\d+)", terminal.getvalue())
    assert drawn and drawn[-1] == ("100", str(steps), str(steps))  # continual 400 + 400; drago 400 + 600


@pytest.mark.slow
def test_task_checkpoint_holds_the_world_model_and_no_training_state(reference):
    for index, path in enumerate(task_checkpoints(reference)):
        data = load_checkpoint(path, kind="task", domain="minigrid")
        assert data["kind"] == "task" and data["task_index"] == index
        model = WorldModel(3, 3, 32, use_crelu=True, squash=True)
        model.load_state_dict(data["world_model"])  # strict: exactly a world model's tensors
        keys = " ".join(all_keys({k: v for k, v in data.items() if k != "config"})).lower()
        assert "optimizer" not in keys and "buffer" not in keys and "exp_avg" not in keys and "rng" not in keys
    # Each task ends with a different world model (it was trained on that task).
    models = [load_checkpoint(p)["world_model"] for p in task_checkpoints(reference)]
    assert all(differs(a, b) for a, b in zip(models, models[1:]))


@pytest.mark.slow
@pytest.mark.parametrize("case", ["wrong-domain", "wrong-kind", "truncated", "foreign-torch-file", "missing",
                                  "garbage", "short-text", "pickle-header-only", "newer-version"])
def test_load_checkpoint_rejects_bad_files_with_one_line(reference, tmp_path, case):
    good = task_checkpoints(reference)[0]
    kwargs = {"kind": "task", "domain": "minigrid"}
    path = tmp_path / "ckpt.pt"
    if case == "wrong-domain":
        path, kwargs = good, {"kind": "task", "domain": "cheetah"}
    elif case == "wrong-kind":
        path, kwargs = good, {"kind": "resume", "domain": "minigrid"}
    elif case == "truncated":
        data = good.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif case == "foreign-torch-file":
        torch.save({"world_model": {"w": torch.zeros(2)}, "kind": "task"}, path)
    elif case == "garbage":
        path.write_bytes(os.urandom(4096))
    elif case == "short-text":
        path.write_bytes(b"junk")
    elif case == "pickle-header-only":
        path.write_bytes(b"\x80\x02")
    elif case == "newer-version":
        save_checkpoint(path, {"world_model": {}}, kind="task", domain="minigrid")
        data = torch.load(path, weights_only=True)
        data["version"] = 99
        torch.save(data, path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path, **kwargs)
    message = str(info.value)
    print(f"{case}: {message}")
    assert message and "\n" not in message


# ---------------------------------------------------------------------------------------------------
# Determinism
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_same_seed_gives_identical_logs_and_another_seed_does_not(reference, tmp_path):
    same, other = tmp_path / "same", tmp_path / "other"
    assert train(same) == 0
    for name in ("train.csv", "eval.csv"):
        assert (same / name).read_bytes() == (reference / name).read_bytes(), name
    assert train(other, "--seed", "2") == 0
    assert (other / "train.csv").read_bytes() != (reference / "train.csv").read_bytes()


@pytest.mark.slow
def test_evaluation_never_changes_what_a_run_learns(reference, tmp_path):
    """Evaluations run on a torch stream and envs of their own: evaluating more often and with more
    episodes leaves the training log byte for byte as it was."""
    out = tmp_path / "more-evals"
    assert train(out, "train.eval_freq=100", "train.eval_episodes=3") == 0
    assert (out / "train.csv").read_bytes() == (reference / "train.csv").read_bytes()
    assert len(read_csv(out / "eval.csv")) == 4 * 5 and len(read_csv(reference / "eval.csv")) == 4 * 3


def test_episodes_side_by_side_are_the_episodes_one_at_a_time():
    from drago.envs import make_env
    from drago.envs.episodes import run_episode, run_episodes

    def fixed(seed):
        return np.random.default_rng(seed).integers(3, size=30)

    def one_hot(index):
        return np.eye(3, dtype=np.float32)[index]

    envs = [make_env("minigrid", "room1", False), make_env("minigrid", "room3", False)]
    for seed, env in enumerate(envs):
        env.reset(seed=seed)
    plans = np.stack([fixed(0), fixed(1)], axis=1)  # (t, env)
    together = run_episodes(envs, 30, lambda obs, t: one_hot(plans[t]))
    for seed, (name, episode) in enumerate(zip(("room1", "room3"), together)):
        env = make_env("minigrid", name, False)
        env.reset(seed=seed)
        alone = run_episode(env, 30, lambda obs, t: one_hot(fixed(seed)[t]))
        for field in ("obs", "actions", "rewards"):
            np.testing.assert_array_equal(getattr(episode, field), getattr(alone, field))
    assert not np.array_equal(together[0].obs, together[1].obs)  # two episodes, not one twice


# ---------------------------------------------------------------------------------------------------
# Chaining the world model from task to task (paper §3.3; docs: Design, how a run flows)
# ---------------------------------------------------------------------------------------------------
def _probe(base: type) -> type:
    class Probe(base):
        begun: dict[int, dict[str, torch.Tensor]] = {}
        ended: dict[int, dict[str, torch.Tensor]] = {}

        def begin_task(self, task):
            super().begin_task(task)
            Probe.begun[task.index] = {k: v.detach().clone() for k, v in task.world_model.state_dict().items()}

        def end_task(self, task):
            super().end_task(task)
            Probe.ended[task.index] = {k: v.detach().clone() for k, v in task.world_model.state_dict().items()}

    return Probe


@pytest.mark.slow
@pytest.mark.parametrize("base", [Continual, Scratch], ids=["continual", "scratch"])
def test_world_model_chaining(base, tmp_path, monkeypatch):
    probe = _probe(base)
    monkeypatch.setitem(METHODS, "probe", probe)
    out = tmp_path / "run"
    assert train(out, "--method", "probe", "env.tasks=[room1,room2]") == 0
    saved = load_checkpoint(out / "checkpoints" / "task1_room1.pt", kind="task")["world_model"]
    assert_same_state(probe.ended[0], saved)  # the checkpoint is the world model task 1 ended with
    assert differs(probe.begun[0], probe.ended[0])  # and task 1 did train it
    if base is Continual:
        assert_same_state(probe.begun[1], saved)
    else:
        assert differs(probe.begun[1], saved)
        # Every tensor is fresh, the EMA target included.
        assert all(not torch.equal(probe.begun[1][k], saved[k]) for k in saved)


# ---------------------------------------------------------------------------------------------------
# Crash and resume
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_resume_after_crash_replays_the_uninterrupted_run(reference, tmp_path):
    run = tmp_path / "crashed"
    # Task 2 has 20 gradient steps (episodes 3 and 4); the periodic checkpoint is at step 200, so the crash
    # comes after episode 3 was logged past that checkpoint.
    with crash_at_gradient_step(Continual, 16, task=1), pytest.raises(SimulatedCrash):
        train(run)
    ckpt = run / "checkpoints"
    assert (ckpt / "resume.pt").is_file() and (ckpt / "task1_room1.pt").is_file()
    assert not (ckpt / "task2_room2.pt").exists()
    snapshot = load_checkpoint(ckpt / "resume.pt", kind="resume")
    assert snapshot["task_index"] == 1 and snapshot["cpu_elapsed"] > 0
    rows = read_csv(run / "train.csv")
    assert rows[-1]["task"] == "room2" and rows[-1]["episode"] == "3"  # a row past the checkpoint
    assert json.loads((run / "summary.json").read_text())["complete"] is False

    assert cli.main(["resume", str(run), "--no-progress"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["complete"] is True and [t["name"] for t in summary["tasks"]] == list(TASKS)
    assert not (ckpt / "resume.pt").exists()
    # Task 2's CPU time counts the work before the crash that the snapshot kept.
    assert summary["tasks"][1]["cpu_time_s"] >= snapshot["cpu_elapsed"]
    for name in ("train.csv", "eval.csv"):
        assert (run / name).read_bytes() == (reference / name).read_bytes(), name
    for mine, ref in zip(task_checkpoints(run), task_checkpoints(reference)):
        assert_same_state(load_checkpoint(mine)["world_model"], load_checkpoint(ref)["world_model"])


@pytest.mark.slow
def test_a_resumed_run_keeps_the_tensorboard_points_logged_up_to_its_checkpoint(tmp_path):
    # TensorBoard forgets what a killed run logged after its checkpoint (purge_step). The rows logged at the
    # checkpoint's own step came before it and must survive: here the evaluation at task 2's periodic
    # checkpoint (env step 200), where the run resumes after a crash on task 2's first update.
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = tmp_path / "run"
    argv = ["train", "smoke", "--out", str(run), "--no-progress", "env.tasks=[room1,room2]"]
    with crash_at_gradient_step(Continual, 1, task=1), pytest.raises(SimulatedCrash):
        cli.main(argv)
    assert cli.main(["resume", str(run), "--no-progress"]) == 0
    events = EventAccumulator(str(run / "tb"))
    events.Reload()
    evals = read_csv(run / "eval.csv")
    for task, offset in (("room1", 0), ("room2", 400)):  # the smoke preset: 400 env steps per task
        logged = [(int(r["env_step"]) + offset, float(r["episode_reward"])) for r in evals if r["task"] == task]
        seen = [(e.step, e.value) for e in events.Scalars(f"eval/{task}/episode_reward")]
        assert [step for step, _ in seen] == [step for step, _ in logged], task
        np.testing.assert_allclose([v for _, v in seen], [v for _, v in logged], rtol=1e-6)


@pytest.mark.slow
def test_a_nan_stops_the_run_in_one_line_and_resume_continues_from_a_sound_checkpoint(
        reference, tmp_path, capsys):
    run = tmp_path / "diverged"
    original = Continual.gradient_step
    calls = {"task2": 0}

    def poisoned_gradient_step(self, task, u):
        metrics = original(self, task, u)
        if task.index == 1:
            calls["task2"] += 1
            if calls["task2"] == 15:  # episode 4 of room 2, after the periodic checkpoint at step 200
                with torch.no_grad():
                    next(task.world_model.dynamics.parameters()).view(-1)[0] = float("nan")
        return metrics

    with pytest.MonkeyPatch.context() as m:
        m.setattr(Continual, "gradient_step", poisoned_gradient_step)
        assert train(run) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("drago: error: [room2] training diverged at task step 400")
    assert "not finite" in err or "is nan" in err
    ckpt = run / "checkpoints"
    assert f"the last good checkpoint is {ckpt / 'resume.pt'}" in err and f"drago resume {run}" in err
    assert not (ckpt / "task2_room2.pt").exists()
    snapshot = load_checkpoint(ckpt / "resume.pt", kind="resume")
    assert snapshot["step"] == 200 and all(torch.isfinite(v).all() for v in snapshot["world_model"].values())

    assert cli.main(["resume", str(run), "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv"):
        assert (run / name).read_bytes() == (reference / name).read_bytes(), name


def test_a_checkpoint_with_a_nan_is_never_written(tmp_path):
    from drago.training.checkpoint import NonFiniteCheckpoint

    path = tmp_path / "task1_room1.pt"
    save_checkpoint(path, {"world_model": {"w": torch.ones(2)}}, kind="task", domain="minigrid")
    before = path.read_bytes()
    with pytest.raises(NonFiniteCheckpoint, match=r"not saving .*: world_model\.w holds a non-finite value"):
        save_checkpoint(path, {"world_model": {"w": torch.tensor([1.0, float("inf")])}}, kind="task",
                        domain="minigrid")
    assert path.read_bytes() == before and not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupt_during_a_checkpoint_write_stops_after_the_write(tmp_path, monkeypatch, signum):
    """Ctrl-C or `kill` while torch writes a checkpoint: the file is whole and loads, and the command stops with
    an interrupt right after (inside torch's zip writer the interrupt surfaced as a RuntimeError instead)."""
    from drago.cli import _terminate_as_interrupt

    class SignalledMidway:
        """The file torch writes to; the signal arrives in the middle of the archive."""

        def __init__(self, handle):
            self.handle, self.writes = handle, 0

        def write(self, data):
            self.writes += 1
            if self.writes == 3:
                os.kill(os.getpid(), signum)
            return self.handle.write(data)

        def flush(self):
            self.handle.flush()

    save = torch.save
    monkeypatch.setattr(torch, "save", lambda obj, handle: save(obj, SignalledMidway(handle)))
    path = tmp_path / "task1_room1.pt"
    tensors = {f"w{i}": torch.full((4096,), float(i)) for i in range(8)}
    with _terminate_as_interrupt(), pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, {"world_model": tensors}, kind="task", domain="minigrid")
    monkeypatch.undo()
    loaded = load_checkpoint(path, kind="task")
    assert all(torch.equal(loaded["world_model"][k], v) for k, v in tensors.items())
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.slow
def test_resume_of_a_complete_run_is_a_no_op(reference, capsys):
    before = {n: (reference / n).read_bytes() for n in ("train.csv", "eval.csv")}
    assert cli.main(["resume", str(reference), "--no-progress"]) == 0
    assert "already complete" in capsys.readouterr().out
    assert before == {n: (reference / n).read_bytes() for n in ("train.csv", "eval.csv")}


@pytest.mark.slow
def test_sigkill_then_resume_finishes_the_sequence(tmp_path):
    """A real crash: SIGKILL inside task 2, after a periodic checkpoint; `drago resume` then finishes the
    sequence and, because the checkpoint carries every RNG state, writes the logs of an uninterrupted run."""
    run = tmp_path / "killed"
    # Frequent checkpoints leave a wide window inside task 2 (killed after its first, at step 100 of 400);
    # a third task follows it.
    tasks = TASKS[:3]
    longer = [f"env.tasks=[{','.join(tasks)}]", "train.checkpoint_freq=100"]
    code = sigkill_in_task_two(["smoke", *QUIET, *longer], run, tmp_path)
    resume_ckpt = run / "checkpoints" / "resume.pt"
    assert code == -signal.SIGKILL
    assert not (run / "checkpoints" / "task3_room3.pt").exists()
    assert load_checkpoint(resume_ckpt, kind="resume")["task_index"] >= 1
    assert not json.loads((run / "summary.json").read_text())["complete"]

    done = subprocess.run([str(DRAGO), "resume", str(run), "--no-progress"], capture_output=True, text=True,
                          env=ONE_THREAD_ENV, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr
    summary = json.loads((run / "summary.json").read_text())
    assert summary["complete"] is True
    assert [t["name"] for t in summary["tasks"]] == list(tasks)
    assert all(t["steps"] == 400 for t in summary["tasks"])
    # The logs hold every episode exactly once: rows written after the last checkpoint were cut back.
    rows = read_csv(run / "train.csv")
    assert [(r["task"], int(r["episode"])) for r in rows] == [(t, e) for t in tasks for e in range(1, 5)]
    evals = read_csv(run / "eval.csv")
    assert [(r["task"], int(r["env_step"])) for r in evals] == [(t, s) for t in tasks for s in (0, 200, 400)]

    # And they are the logs of the same run never interrupted.
    uninterrupted = tmp_path / "uninterrupted"
    assert train(uninterrupted, *longer) == 0
    for name in ("train.csv", "eval.csv"):
        assert (run / name).read_bytes() == (uninterrupted / name).read_bytes(), name


RESIDENT_AFTER_A_FREED_TENSOR = """
import os, torch
from drago.training.resources import keep_freed_memory

def resident_mib():
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

print(keep_freed_memory())
before = resident_mib()
torch.ones(2**24).sum()  # 64 MiB, freed at once
print(resident_mib() - before)
"""


@pytest.mark.slow
@pytest.mark.skipif(sys.platform != "linux", reason="glibc's allocator and Linux's /proc")
@pytest.mark.parametrize("opt_out", [False, True])
def test_freed_memory_stays_with_the_process_for_reuse_unless_opted_out(opt_out):
    """What a run's allocator setting does: a freed 64 MiB tensor stays resident, for the next allocation to
    reuse; with glibc's defaults it goes back to the kernel at once. (How many page faults that saves:
    benchmarks/memory_reuse.py.)"""
    env = {**os.environ, "DRAGO_KEEP_FREED_MEMORY": "0" if opt_out else "1"}
    out = subprocess.run([sys.executable, "-c", RESIDENT_AFTER_A_FREED_TENSOR], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    applied, kept_mib = out[0] == "True", float(out[1])
    assert applied is not opt_out
    if opt_out:
        assert kept_mib < 16
    else:
        assert kept_mib > 60


@pytest.mark.parametrize("value", ["0", "false", "No", " off "])
def test_every_spelling_of_no_keeps_the_allocator_defaults(value, monkeypatch):
    monkeypatch.setenv("DRAGO_KEEP_FREED_MEMORY", value)
    assert keep_freed_memory() is False


PEAK_AFTER_A_LARGE_FREED_TENSOR = """
import torch
from drago.training.resources import PeakMemory, keep_freed_memory
assert keep_freed_memory()
torch.ones(2**27).sum()  # 512 MiB, freed at once but kept by malloc
memory = PeakMemory()
memory.start()
torch.ones(2**24).sum()  # 64 MiB
print(memory.read()["peak_rss_mib"])
"""


@pytest.mark.slow
@pytest.mark.skipif(sys.platform != "linux", reason="glibc's allocator and Linux's resettable peak RSS")
def test_peak_memory_of_a_stretch_excludes_memory_kept_from_earlier_ones():
    env = {**os.environ, "DRAGO_KEEP_FREED_MEMORY": "1"}
    out = subprocess.run([sys.executable, "-c", PEAK_AFTER_A_LARGE_FREED_TENSOR], env=env, capture_output=True,
                         text=True, check=True).stdout
    assert float(out) < 512
