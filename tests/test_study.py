"""`drago study`: every method x seed, their transfer cases and the report, resumable (README "The grid study").

Studies here are tiny `smoke` runs (four tasks of two episodes, transfers of one episode) run in this
process, so that a crash can be injected; one test runs the real child processes.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from drago import cli
from drago.continual.naive import Continual
from drago.study import local
from drago.study.local import run_study
from drago.study.plan import (DONE, RESUME, START, StudyError, available_cores, describe_plan, parse_cases, parse_seeds,
                              plan_study)
from drago.study.slurm.submission import report_argv
from helpers import crash_at_gradient_step, wait_for

METHODS = ("continual", "scratch")
TINY = ["train.steps_per_task=200", "agent.seed_steps=100", "train.checkpoint_freq=100", "train.tensorboard=false",
        "agent.tdmpc.mlp_dim=16", "agent.batch_size=16", "agent.tdmpc.iterations=1", "agent.tdmpc.num_samples=8", "agent.tdmpc.num_elites=2",
        "train.threads=1"]
CASES = ("room1to2-after2", "room1to3-after3", "room1to3-after4", "room3to4-after4")
LOGS = ("train.csv", "eval.csv")


def plan(out: Path, *extra: str, methods=METHODS, episodes: int = 1, **options):
    return plan_study("smoke", methods, [1], out=out, overrides=[*TINY, *extra], transfer_episodes=episodes, **options)


def study_argv(out: Path, *extra: str) -> list[str]:
    return ["study", "smoke", "--methods", *METHODS, "--seeds", "1", "--out", str(out), "--transfer-episodes", "1",
            *TINY, *extra]


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def snapshot(root: Path) -> dict[str, bytes]:
    """Every log of every run and transfer below ``root``."""
    return {str(p.relative_to(root)): p.read_bytes() for name in LOGS for p in sorted(root.rglob(name))}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """A complete, uninterrupted study of two methods and one seed."""
    out = tmp_path_factory.mktemp("study") / "ref"
    result = run_study(plan(out), echo=lambda line: None, in_process=cli.main)
    assert result.ok, result.summary_line()
    return out


# ---------------------------------------------------------------------------------------------------
# The plan
# ---------------------------------------------------------------------------------------------------
def test_default_plan_is_the_grid_study(tmp_path, capsys):
    out = tmp_path / "grid"
    assert cli.main(["study", "--dry-run", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "drago study minigrid-cpu" in text
    assert "7 methods x 3 seeds = 21 runs of room1 -> room2 -> room3 -> room4" in text
    assert "runs:      21 to start, 0 to resume, 0 finished" in text
    assert "transfers: 84 to start" in text and "room1to3 after 4" in text and "20 learner episodes each" in text
    # Every learner gets the same 10k steps a task; DRAGO's reviewer up to 5k more (the preset's separate budgets).
    assert ("budget:    10,000 learner steps a task for every method, up to 5,000 more for DRAGO's reviewer; "
            "the official code's shared accounting: train.learner_steps_per_task=null "
            "train.reviewer_steps_per_task=null; schedules counted in the learner's steps (the official clock: "
            "agent.schedule_clock=task)") in text
    for method in ("drago", "continual", "ewc", "scratch", "replay", "drago-no-rehearsal", "drago-no-reviewer"):
        for seed in (1, 2, 3):
            assert f"{method} seed{seed}" in text
    assert not out.exists()  # a dry run writes nothing


def test_dry_run_of_a_short_sequence_leaves_out_the_cases_it_cannot_run(tmp_path, capsys):
    out = tmp_path / "short"
    assert cli.main([*study_argv(out, "env.tasks=[room1,room2]"), "--jobs", "2", "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "2 methods x 1 seed = 2 runs of room1 -> room2" in text
    assert "transfers: 2 to start" in text and "cases room1to2 after 2," in text
    assert "left out" in text and "room1to3 after 3, room1to3 after 4, room3to4 after 4" in text
    assert "2 at a time" in text
    assert not out.exists()

    # No transfers asked: none planned; threads follow --jobs when no override sets them.
    bare = plan_study("smoke", ["continual"], [1], out=out, transfers=False, jobs=2, cores=4)
    assert bare.transfers == [] and bare.threads == 2 and "train.threads=2" in bare.runs[0].argv

    # Dense transfers beside the task's own sparse ones: directories, logs and commands of their own.
    dense = plan_study("smoke", ["continual"], [1], out=out, transfer_reward="dense", transfer_episodes=50)
    job = next(j for j in dense.transfers if j.case == ("room1to2", 2))
    assert job.directory == out / "continual" / "seed1" / "transfer" / "room1to2-dense-after2"
    assert job.log.name == "continual-seed1-room1to2-dense-after2.log"
    assert job.argv[job.argv.index("--reward") + 1] == "dense" and "50" in job.argv
    assert "50 learner episodes each with dense reward" in describe_plan(dense)[4]

    # Cases of one's own: a training room relearned from the last stage, read after all 40 episodes. The report
    # job of a SLURM study reruns the study command, which must name the same cases.
    own = plan_study("smoke", ["continual"], [1], out=out, cases=[("room1", 2), ("room1to2", 1)],
                     transfer_episodes=40, transfer_few_shot_episodes=40, transfer_eval_every=10)
    assert [j.case for j in own.transfers] == [("room1", 2), ("room1to2", 1)]
    assert own.transfers[0].argv[own.transfers[0].argv.index("--few-shot-episodes") + 1] == "40"
    argv = report_argv(own)
    assert argv[argv.index("--cases") + 1:argv.index("--cases") + 3] == ["room1:2", "room1to2:1"]
    assert "--cases" not in report_argv(bare)  # the paper's cases need no flag
    with pytest.raises(StudyError, match="between 1 and 4"):
        plan_study("smoke", ["continual"], [1], out=out, cases=[("room1", 5)])
    with pytest.raises(StudyError, match="TASK:K"):
        parse_cases(["room1to2"])
    with pytest.raises(StudyError, match="grid only"):  # refused before any run, not by each transfer after it
        plan_study("cheetah-cpu", ["continual"], [1], out=out, transfer_reward="dense")

    # Separate budgets: what every learner gets, what DRAGO's reviewer adds, and the way back to the shared one.
    separate = plan_study("smoke", ["drago"], [1], out=out, overrides=["train.learner_steps_per_task=400",
                                                                      "train.reviewer_steps_per_task=200"])
    assert separate.budget == ("400 learner steps a task for every method, up to 200 more for DRAGO's reviewer; "
                               "the official code's shared accounting: train.learner_steps_per_task=null "
                               "train.reviewer_steps_per_task=null; schedules counted in the learner's steps (the "
                               "official clock: agent.schedule_clock=task)")
    # No method with a second agent: the clock changes nothing, and the line does not mention it.
    assert "clock" not in plan_study("smoke", ["continual"], [1], out=out).budget


def test_seeds_and_ranges():
    assert parse_seeds(["1-3"]) == [1, 2, 3]
    assert parse_seeds(["2", "1-3", "5"]) == [2, 1, 3, 5]
    for bad in ("3-1", "x", "-1", "1-"):
        with pytest.raises(StudyError, match="--seeds"):
            parse_seeds([bad])


# ---------------------------------------------------------------------------------------------------
# A study and its re-invocation
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_study_writes_runs_transfers_logs_and_report(reference):
    for method in METHODS:
        run = reference / method / "seed1"
        summary = json.loads((run / "summary.json").read_text())
        assert summary["complete"] is True and summary["method"] == method and len(summary["tasks"]) == 4
        assert (reference / "logs" / f"{method}-seed1.log").is_file()
        for case in CASES:
            transfer = json.loads((run / "transfer" / case / "summary.json").read_text())
            assert transfer["complete"] is True and transfer["transfer"]["episodes_planned"] == 1
            assert f"{transfer['transfer']['task']}-after{transfer['transfer']['after']}" == case
            assert (reference / "logs" / f"{method}-seed1-{case}.log").is_file()
    report = reference / "report"
    for name in ("report.html", "report.md", "transfers.csv", "transfers.md"):
        assert (report / name).is_file(), name
    rows = read_csv(report / "transfers.csv")
    assert sorted((r["method"], f"{r['task']}-after{r['after']}") for r in rows) == sorted(
        (m, c) for m in METHODS for c in CASES)
    assert "| room3to4 after 4 | 88.0 |" in (report / "transfers.md").read_text()


@pytest.mark.slow
def test_second_invocation_only_rebuilds_the_report(reference, capsys):
    before = snapshot(reference)
    (reference / "report" / "report.html").unlink()
    assert cli.main(study_argv(reference)) == 0
    text = capsys.readouterr().out
    assert "runs:      0 to start, 0 to resume, 2 finished" in text
    assert "transfers: 0 to start, 0 to resume, 8 finished" in text
    assert "[1/" not in text  # no job ran
    assert "study complete: 0 jobs run, 10 already finished" in text
    assert (reference / "report" / "report.html").is_file()
    assert snapshot(reference) == before


@pytest.mark.slow
def test_crash_then_the_same_command_finishes_with_the_logs_of_an_uninterrupted_study(
        reference, tmp_path, monkeypatch, capsys):
    out = tmp_path / "crashed"
    # The CLI's child processes run in this process here, so that the crash below reaches them.
    monkeypatch.setattr(local, "_launch_process", lambda job: local._launch_in_process(job, cli.main))
    with crash_at_gradient_step(Continual, 5, task=2):  # episode 2 of room 3, after its checkpoint at step 100
        assert cli.main(study_argv(out)) == 1
    captured = capsys.readouterr()
    log = out / "logs" / "continual-seed1.log"
    assert "FAILED  continual seed1 (exit 1)" in captured.out
    assert "not started: continual seed1 room1to2-after2 (its run failed)" in captured.out
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("drago: study incomplete: 1 job failed")
    assert str(log) in err and "4 transfers not started" in err and "run the same command again" in err
    assert "simulated crash" in log.read_text()
    assert (out / "continual" / "seed1" / "checkpoints" / "resume.pt").is_file()
    assert not (out / "continual" / "seed1" / "transfer").exists()
    assert (out / "report" / "report.html").is_file()  # the report shows what there is
    scratch = snapshot(out / "scratch")
    assert len(scratch) == 2 * (1 + len(CASES))

    again = plan(out)
    assert [(j.label, j.state) for j in again.runs] == [("continual seed1", RESUME), ("scratch seed1", DONE)]
    assert [j.state for j in again.transfers] == [START] * 4 + [DONE] * 4
    # The finished jobs' wall times give an estimate of what is left.
    assert any(line.startswith("  time:      about") for line in describe_plan(again))
    assert cli.main(study_argv(out)) == 0
    text = capsys.readouterr().out
    jobs = [line for line in text.splitlines() if line.startswith("[")]
    assert len(jobs) == 5 and jobs[0].startswith("[1/5] done    continual seed1 in")
    assert not any("scratch" in line for line in jobs)
    assert snapshot(out / "scratch") == scratch  # finished work was not redone
    assert snapshot(out) == snapshot(reference)  # byte-identical train.csv and eval.csv everywhere


def test_runs_start_before_the_transfers_they_unlock(tmp_path, monkeypatch):
    started = []

    def launch(job, command):
        started.append(job.label)
        return local._Done(0)

    monkeypatch.setattr(local, "_launch_in_process", launch)
    p = plan(tmp_path / "order", methods=("continual", "scratch"), jobs=1)
    run_study(p, echo=lambda line: None, in_process=cli.main)
    assert started[:2] == ["continual seed1", "scratch seed1"]
    assert sorted(started[2:]) == sorted(j.label for j in p.transfers) and len(started) == 2 + 2 * len(CASES)


def test_a_job_that_exits_with_an_error_fails_the_study_and_points_at_its_log(tmp_path):
    out = tmp_path / "failing"
    p = plan(out, methods=("continual",))
    p.runs[0].argv = ["resume", str(out / "elsewhere"), "--no-progress"]  # exits 2: not a run directory
    lines = []
    result = run_study(p, echo=lines.append, in_process=cli.main)
    log = out / "logs" / "continual-seed1.log"
    assert not result.ok and result.failed == p.runs and p.runs[0].returncode == 2
    assert [j.status for j in p.transfers] == ["blocked"] * 4 and result.blocked == p.transfers
    assert "drago: error: run directory" in log.read_text() and "does not exist" in log.read_text()
    assert f"log: {log}" in lines[0] and str(log) in result.summary_line()
    assert result.report_error == "no run of the study has started"


# ---------------------------------------------------------------------------------------------------
# Refusals
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("case", ["other-setting", "other-transfer-episodes", "not-a-run", "locked"])
def test_a_folder_holding_something_else_is_a_one_line_error(reference, tmp_path, capsys, case):
    argv = study_argv(reference)
    if case == "other-setting":
        argv.append("train.steps_per_task=300")
        expected = (str(reference / "continual" / "seed1"), "train.steps_per_task: 200 there, 300 here", "--out",
                    "delete")
    elif case == "other-transfer-episodes":
        argv[argv.index("--transfer-episodes") + 1] = "2"
        expected = (str(reference / "continual" / "seed1" / "transfer" / "room1to2-after2"), "--out")
    elif case == "not-a-run":
        out = tmp_path / "study"
        (out / "scratch" / "seed1").mkdir(parents=True)
        (out / "scratch" / "seed1" / "notes.txt").write_text("mine")
        argv = study_argv(out)
        expected = (str(out / "scratch" / "seed1"), "not a drago run")
    else:
        import fcntl

        handle = (reference / local.LOCK_FILE).open("w")
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        expected = ("another `drago study`", str(reference))
    try:
        capsys.readouterr()
        assert cli.main(argv) == 2
    finally:
        if case == "locked":
            handle.close()
    err = capsys.readouterr().err.strip()
    assert err.startswith("drago: error: ") and len(err.splitlines()) == 1 and "Traceback" not in err
    for text in expected:
        assert text in err, text


@pytest.mark.slow
def test_transfers_evaluated_every_n_episodes_and_kept_to_that_setting(tmp_path):
    out = tmp_path / "every2"
    result = run_study(plan(out, methods=("continual",), episodes=2, transfer_eval_every=2), echo=lambda line: None,
                       in_process=cli.main)
    assert result.ok, result.summary_line()
    for case in CASES:
        evaluations = read_csv(out / "continual" / "seed1" / "transfer" / case / "eval.csv")
        assert [r["episode"] for r in evaluations] == ["0", "2"]
    again = plan(out, methods=("continual",), episodes=2, transfer_eval_every=2)
    assert {job.state for job in [*again.runs, *again.transfers]} == {DONE}
    with pytest.raises(StudyError, match="room1to2-after2"):
        plan(out, methods=("continual",), episodes=2, transfer_eval_every=1)


@pytest.mark.parametrize("argv, expected", [
    (["--jobs", "0"], "--jobs"),
    (["--seeds", "x"], "--seeds"),
    (["--methods", "nope"], "nope"),
    (["--transfer-episodes", "0"], "--transfer-episodes"),
    (["--transfer-eval-every", "0"], "--transfer-eval-every"),
    (["--transfer-eval-every", "3"], "does not divide the 20 few-shot episodes"),
    (["agent.nope=1"], "nope"),
])
def test_bad_arguments_are_one_line_errors(tmp_path, capsys, argv, expected):
    assert cli.main(["study", "smoke", "--out", str(tmp_path / "s"), "--dry-run", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drago: error: ") and len(err.splitlines()) == 1 and expected in err


# ---------------------------------------------------------------------------------------------------
# Child processes
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_jobs_run_in_parallel_child_processes_with_their_own_logs(tmp_path, capsys, monkeypatch):
    out = tmp_path / "parallel"
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    argv = ["study", "smoke", "--methods", "scratch", "--seeds", "1-2", "--out", str(out), "--jobs", "2",
            "--no-transfer", "env.tasks=[room1]", *TINY[:-1], "train.steps_per_task=100"]
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert "2 at a time on" in text and "train.threads=" in text and "done    scratch seed2" in text
    for seed in (1, 2):
        log = (out / "logs" / f"scratch-seed{seed}.log").read_text()
        assert f"drago train smoke --method scratch --seed {seed}" in log and "Traceback" not in log
        assert json.loads((out / "scratch" / f"seed{seed}" / "summary.json").read_text())["complete"] is True
    threads = {yaml.safe_load((out / "scratch" / f"seed{s}" / "config.yaml").read_text())["train"]["threads"]
               for s in (1, 2)}
    assert threads == {max(1, available_cores() // 2)}
    assert (out / "report" / "report.html").is_file()


def alive(pid: int) -> bool:
    try:  # the third field of /proc/PID/stat is the state; Z: a zombie, dead but not yet reaped
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_dies_with_its_study(tmp_path):
    """A SIGKILLed study leaves no orphan that would race the next study for a run directory."""
    pid_file = tmp_path / "child.pid"
    child = ("import os, time; from drago.study.local import _die_with_parent; _die_with_parent(); "
             f"open({str(pid_file)!r}, 'w').write(str(os.getpid())); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", "import subprocess, sys, time; "
                               f"subprocess.Popen([sys.executable, '-c', {child!r}]); time.sleep(60)"])

    def child_started() -> bool:
        assert parent.poll() is None, f"the parent ended (rc {parent.returncode}) before its child started"
        return pid_file.is_file() and bool(pid_file.read_text())

    try:
        wait_for(child_started, 30, "the child to start", interval=0.05)
        pid = int(pid_file.read_text())
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        wait_for(lambda: not alive(pid), 10, "the child to die with its parent (it outlived it)", interval=0.05)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if pid_file.is_file() and pid_file.read_text() and alive(int(pid_file.read_text())):
            os.kill(int(pid_file.read_text()), signal.SIGKILL)


@pytest.mark.slow
def test_sigterm_stops_a_background_study_and_its_jobs_like_ctrl_c(tmp_path):
    """Started from a script in the background a study ignores SIGINT; `kill PID` stops it cleanly, and it
    stops its jobs the same way, so the same command continues it."""
    out = tmp_path / "killed"
    argv = [sys.executable, "-c", "import sys; from drago.cli import main; sys.exit(main(sys.argv[1:]))",
            *study_argv(out, "train.steps_per_task=100000"), "--no-transfer"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    train_csv, job_log = out / "continual" / "seed1" / "train.csv", out / "logs" / "continual-seed1.log"

    def episodes_logged() -> int:
        assert proc.poll() is None, f"the study ended (rc {proc.returncode})"
        return max(0, len(train_csv.read_text().splitlines()) - 1) if train_csv.is_file() else 0

    try:
        wait_for(lambda: episodes_logged() > 0, 180, "the first job to log an episode", interval=0.1)
        proc.send_signal(signal.SIGINT)  # ignored, as after `drago study ... &` in a script
        # Ignored by the study, which keeps its job training: two more episodes, and the job was never told to stop
        # (a job stopped at the end of its episode would log at most one).
        logged = episodes_logged()
        wait_for(lambda: episodes_logged() >= logged + 2, 180, "two more episodes after SIGINT", interval=0.1)
        assert "drago: interrupted" not in job_log.read_text()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130
    assert err.strip().splitlines()[-1].startswith("drago: interrupted; run the same `drago study` command again")
    # The job stopped on its signal (a job killed after the study's wait would not have said so).
    assert "drago: interrupted" in job_log.read_text()
    assert [(j.label, j.state) for j in plan(out, "train.steps_per_task=100000", transfers=False).runs] == [
        ("continual seed1", RESUME), ("scratch seed1", START)]
