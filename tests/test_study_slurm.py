"""`drago study --backend slurm` (docs: Running on a cluster), against a real one-node SLURM (tests/slurm_cluster.py).

The first tests need no cluster: the dry run's sbatch options, the one-line refusals, how runs share GPUs. The others
submit tiny `smoke` studies to the test cluster as a user would, with `python -m drago study ...` in a subprocess:
a study through to its report; a job `scancel`ed in the middle, and one stopped by its time limit (an
experiment), finishing after the same command is run again with train.csv and eval.csv byte-identical to an
uninterrupted study; a second command while the jobs are queued submits nothing; a folder the nodes cannot see, and
a partition SLURM does not know, are one-line errors. Where the cluster cannot start they are skipped with the
reason. Every wait is bounded.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from drago import cli
from drago.study.local import run_study
from drago.study.plan import StudyError, plan_study
from drago.study.slurm.node import Member, StudyJob, gpu_for
from drago.study.slurm.options import make_options, parse_time

# The fixtures slurm_cluster (session) and slurm_env (per test) come from tests/slurm_cluster.py, a plugin module.
pytest_plugins = ("slurm_cluster",)
pytest.register_assert_rewrite("slurm_cluster")
from slurm_cluster import SlurmCluster, wait_for  # noqa: E402

METHODS = ("continual", "scratch")
# Two rooms of 600 steps (6 episodes), a checkpoint every 100: a few seconds a run, long enough to stop in the middle.
TINY = ["env.tasks=[room1,room2]", "train.steps_per_task=600", "agent.seed_steps=100", "train.checkpoint_freq=100",
        "train.tensorboard=false", "agent.tdmpc.mlp_dim=16", "agent.batch_size=16", "agent.tdmpc.iterations=1",
        "agent.tdmpc.num_samples=8", "agent.tdmpc.num_elites=2", "train.threads=1"]
LOGS = ("train.csv", "eval.csv")
RUN = Path("continual") / "seed1"
TRANSFER = RUN / "transfer" / "room1to2-after2"


def study_argv(out: Path, *extra: str, methods=("continual",), seeds=("1",), settings=TINY) -> list[str]:
    return ["study", "smoke", "--methods", *methods, "--seeds", *seeds, "--out", str(out), "--transfer-episodes", "1",
            *settings, "--backend", "slurm", *extra]


def drago(*argv: str, timeout: float = 120, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """`python -m drago ARGS` as a user would type it (SLURM_CONF comes from the slurm_env fixture)."""
    return subprocess.run([sys.executable, "-m", "drago", *argv], check=False, capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, stdin=subprocess.DEVNULL)


def snapshot(root: Path) -> dict[str, bytes]:
    """Every train.csv and eval.csv below ``root``."""
    return {str(p.relative_to(root)): p.read_bytes() for name in LOGS for p in sorted(root.rglob(name))}


def reference_study(out: Path, settings: list[str]) -> Path:
    """An uninterrupted local study of continual seed 1 and its transfer, run in this process."""
    plan = plan_study("smoke", ["continual"], [1], out=out, overrides=settings, transfer_episodes=1)
    result = run_study(plan, echo=lambda line: None, in_process=cli.main)
    assert result.ok, result.summary_line()
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    return reference_study(tmp_path_factory.mktemp("reference") / "study", TINY)


def jobs_file(out: Path) -> dict:
    return json.loads((out / "slurm" / "jobs.json").read_text())


def job_of(out: Path, label: str) -> str:
    return jobs_file(out)["latest"][label]


# ---------------------------------------------------------------------------------------------------
# Without a cluster: the plan, the options, the refusals
# ---------------------------------------------------------------------------------------------------
def test_dry_run_shows_the_sbatch_options_of_every_job(tmp_path, capsys):
    out = tmp_path / "dry"
    argv = study_argv(out, "--partition", "gpu", "--account", "lab", "--qos", "high", "--time", "1:30:00",
                      "--cpus", "4", "--gpus", "1", "--jobs-per-gpu", "2", "--mem", "16G", "--jobs", "3",
                      "--sbatch=--constraint=h100 --exclude node7", "--dry-run", methods=METHODS, seeds=("1-2",),
                      settings=TINY[:-1])  # no train.threads: the study sets it from --cpus
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    print(text)
    assert "slurm:     partition gpu, account lab, QoS high; each job 90 min, 4 CPUs, 1 GPU, 2 runs per GPU" in text
    assert "at most 3 running at once (--jobs)" in text and "train.threads=2" in text
    jobs = [line for line in text.splitlines() if line.startswith("  JOB")]
    # Two runs share each GPU job; the transfers of those two runs share one, after it; the report waits for all.
    assert jobs == ["  JOB1: continual seed1 + scratch seed1", "  JOB2: continual seed2 + scratch seed2",
                    "  JOB3: continual seed1 room1to2-after2 + scratch seed1 room1to2-after2",
                    "  JOB4: continual seed2 room1to2-after2 + scratch seed2 room1to2-after2", "  JOB5: report"]
    sbatch = [line.strip() for line in text.splitlines() if line.strip().startswith("sbatch ")]
    for line in sbatch[:4]:
        for flag in ("--partition=gpu", "--account=lab", "--qos=high", "--time=90", "--cpus-per-task=4",
                     "--gpus-per-node=1", "--mem=16G", "--constraint=h100", "--exclude=node7", "--requeue",
                     "--kill-on-invalid-dep=yes", "--signal=USR2@90", f"--chdir={out.absolute()}"):
            assert flag in line.split(), (flag, line)
    assert "--dependency=singleton" in sbatch[0] and "--dependency=afterok:JOB1,singleton" in sbatch[2]
    assert "--dependency=afterok:JOB2,singleton" in sbatch[3]
    assert "--dependency=afterany:JOB1:JOB2:JOB3:JOB4" in sbatch[4] and "--gpus-per-node" not in sbatch[4]
    assert len({line.split("--job-name=")[1].split()[0] for line in sbatch[:4]}) == 3  # three lanes
    runs = [line.strip() for line in text.splitlines() if line.strip().startswith("runs: python")]
    assert runs[0].startswith("runs: python -m drago train smoke --method continual --seed 1 --out ")
    assert "train.device=cuda" in runs[0] and "train.threads=2" in runs[0]
    assert "--report-only" in runs[-1] and "train.device=cuda" in runs[-1]
    assert not out.exists()  # a dry run writes nothing


def test_gpus_are_not_shared_unless_asked():
    assert [gpu_for(i, 2, 1, "4,5") for i in range(2)] == ["4", "5"]  # a GPU per run, SLURM's numbering
    assert [gpu_for(i, 1, 3, "0") for i in range(3)] == ["0", "0", "0"]  # --jobs-per-gpu 3
    assert [gpu_for(i, 2, 2, None) for i in range(4)] == ["0", "0", "1", "1"]
    assert gpu_for(0, 0, 1, "0") is None
    assert make_options(gpus=1, jobs_per_gpu=3).runs_per_job == 3 and make_options(gpus=2).runs_per_job == 2
    assert make_options().runs_per_job == 1


def test_time_limits_in_slurms_formats():
    assert [parse_time(t) for t in ("90", "1:30:00", "2-0", "0-1:30", "45:30", "1-00:00:01")] == [
        90, 90, 2880, 90, 46, 1441]
    for bad in ("0", "0:59", "1h", "", "infinite"):
        with pytest.raises(StudyError, match="--time"):
            parse_time(bad)


@pytest.mark.parametrize("argv, expected", [
    (["--backend", "local", "--partition", "debug"], "--partition is a SLURM option: add --backend slurm"),
    (["--time", "1h"], "--time takes minutes or SLURM's [D-]HH:MM:SS, got '1h'"),
    (["--cpus", "0"], "--cpus must be a positive integer"),
    (["--jobs", "0"], "--jobs must be a positive integer"),
    (["--jobs-per-gpu", "2"], "--jobs-per-gpu shares a GPU between runs: it needs --gpus 1 or more"),
    (["--mem", "lots"], "--mem takes a size like 16G"),
    (["--sbatch=--partition=x"], "--sbatch cannot set --partition: use drago study's --partition"),
    (["--sbatch=--dependency=afterok:1"], "--sbatch cannot set --dependency: the study sets it"),
    (["--sbatch=-C a100"], "--sbatch takes long sbatch options"),
    (["--status", "--dry-run"], "--dry-run and --status do not go together"),
])
def test_bad_slurm_arguments_are_one_line_errors(tmp_path, capsys, argv, expected):
    assert cli.main([*study_argv(tmp_path / "s", "--dry-run" if "--dry-run" not in argv else "--wait"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drago: error: ") and len(err.splitlines()) == 1 and expected in err, err


def test_without_submitit_the_error_says_how_to_install_it(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "submitit", None)  # import submitit raises ImportError
    assert cli.main(study_argv(tmp_path / "s")) == 2
    err = capsys.readouterr().err.strip()
    assert err == "drago: error: --backend slurm needs submitit, which is not installed: pip install -e '.[slurm]'"


@pytest.mark.slow
def test_loading_submitit_leaves_the_callers_logging_alone():
    # submitit's own logging set-up closes every existing handler (absl's closes its stream with it); a user's
    # handler must survive the study's import, and the environment the jobs inherit must be the caller's.
    pytest.importorskip("submitit")
    code = """
import logging, os
closed = []
class Mine(logging.StreamHandler):
    def close(self):
        closed.append(True)
        super().close()
logging.getLogger("mine").addHandler(Mine())
from drago.study.slurm.options import require_submitit
require_submitit()
print(closed, os.environ.get("SUBMITIT_LOG_LEVEL"))
"""
    env = {k: v for k, v in os.environ.items() if k != "SUBMITIT_LOG_LEVEL"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[]", "None"]


def test_without_sbatch_the_error_says_where_to_run(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no SLURM commands here
    assert cli.main(study_argv(tmp_path / "s")) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drago: error: --backend slurm needs SLURM's sbatch, squeue, scancel on the PATH")


@pytest.mark.slow
def test_status_of_a_local_study_reads_the_directories(reference, capsys):
    assert cli.main(["study", "smoke", "--methods", "continual", "--seeds", "1", "--out", str(reference),
                     "--transfer-episodes", "1", *TINY, "--status"]) == 0
    text = capsys.readouterr().out
    assert "  done     continual seed1 " in text and "  done     continual seed1 room1to2-after2 " in text
    assert "2 done, 0 running, 0 queued, 0 failed, 0 to do" in text and str(reference / "report") in text


# ---------------------------------------------------------------------------------------------------
# The function a SLURM job runs, called here without SLURM
# ---------------------------------------------------------------------------------------------------
def _members(out: Path, settings: list[str], methods=("continual",)) -> list[Member]:
    plan = plan_study("smoke", methods, [1], out=out, overrides=settings, transfers=False)
    return [Member(j.label, j.kind, str(j.directory), j.argv, str(j.log), j.threads) for j in plan.runs]


@pytest.mark.slow
def test_a_job_runs_its_runs_side_by_side_each_on_its_gpu(tmp_path, monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "5,6")  # as SLURM sets it for a job given two GPUs
    settings = [*TINY, "train.steps_per_task=200"]
    members = _members(tmp_path / "shared", settings, methods=METHODS)
    job = StudyJob(members, gpus=2, jobs_per_gpu=1, time_limit_s=600)
    assert job() == {"continual seed1": 0, "scratch seed1": 0}
    for member, device in zip(members, ("5", "6")):
        log = Path(member.log).read_text()
        assert f"drago train smoke --method {member.label.split()[0]}" in log
        assert f"CUDA_VISIBLE_DEVICES={device})" in log
        assert json.loads((Path(member.directory) / "summary.json").read_text())["complete"] is True
    assert job() == {}  # requeued after finishing: nothing left to do
    assert "is complete: nothing to do" in Path(members[0].log).read_text()


@pytest.mark.slow
def test_stopped_near_the_time_limit_a_job_requeues_and_resumes_identically(reference, tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    members = _members(tmp_path / "study", TINY)
    run_dir = Path(members[0].directory)
    job = StudyJob(members, time_limit_s=600)
    with ThreadPoolExecutor(1) as pool:
        attempt = pool.submit(job)
        wait_for(lambda: (run_dir / "checkpoints" / "resume.pt").exists() or attempt.done(), 120,
                 "the first periodic checkpoint", interval=0.05)
        requeued = job.checkpoint()  # what submitit calls on SLURM's USR2 (then it requeues the job and exits)
        with contextlib.suppress(RuntimeError):  # the stopped drago's exit, however this thread saw it
            attempt.result(timeout=60)
    assert requeued is not None
    log = Path(members[0].log).read_text()
    assert "drago: interrupted" in log and "requeued, it continues from the last checkpoint" in log
    # submitit saves what is requeued and loads it in the requeued job:
    requeued.dump(tmp_path / "requeued.pkl")
    assert requeued.load(tmp_path / "requeued.pkl").result() == {"continual seed1": 0}
    assert f"drago resume {run_dir}" in Path(members[0].log).read_text()
    expected = {k: v for k, v in snapshot(reference / RUN).items() if not k.startswith("transfer")}
    assert snapshot(run_dir) == expected and len(expected) == 2


@pytest.mark.slow
def test_a_job_that_wrote_no_checkpoint_in_most_of_its_time_is_not_requeued(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    members = _members(tmp_path / "study", TINY)
    job = StudyJob(members, time_limit_s=2)
    with ThreadPoolExecutor(1) as pool:
        attempt = pool.submit(job)
        log = Path(members[0].log)
        wait_for(lambda: log.is_file() and "drago train" in log.read_text(), 60, "the job to start drago",
                 interval=0.05)
        time.sleep(1.0)  # half the job's time limit since it started: most of its time, drago still starting
        assert job.checkpoint() is None
        with contextlib.suppress(RuntimeError):
            attempt.result(timeout=60)
    assert "without a new checkpoint: not requeued" in Path(members[0].log).read_text()


# ---------------------------------------------------------------------------------------------------
# Against the one-node test cluster
# ---------------------------------------------------------------------------------------------------
@pytest.mark.experiment
def test_smoke_study_runs_to_completion_through_slurm(slurm_env: SlurmCluster, reference, tmp_path):
    """The uninterrupted path, two methods side by side (an experiment: the default suite's cancelled-job test
    below walks the same path after its cancellation and checks the finished study the same way)."""
    c = slurm_env
    out = tmp_path / "smoke"
    t0 = time.monotonic()
    proc = drago(*study_argv(out, "--wait", methods=METHODS), timeout=600, cwd=tmp_path)
    print(f"\n{proc.stdout}{proc.stderr}\nstudy through SLURM: {time.monotonic() - t0:.0f} s")
    print("sinfo:\n" + c.run(["sinfo"]).stdout)
    print("squeue -t all:\n" + c.squeue("%.6i %.40j %.10T %.10M %R", all_states=True))
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    assert "checked: the nodes see the study folder" in text
    assert text.count("submitted job ") == 5  # 2 runs, 2 transfers, the report
    assert "after job" in text and "study complete: 4 jobs run through SLURM, 0 already finished" in text
    finished = [line for line in text.splitlines() if line.startswith("[")]
    assert len(finished) == 4 and all("] done    " in line for line in finished)
    states = c.job_states()
    record = jobs_file(out)
    assert all(states[job_id] == "COMPLETED" for job_id in record["jobs"])
    for method in METHODS:
        summary = json.loads((out / method / "seed1" / "summary.json").read_text())
        assert summary["complete"] is True
        log = (out / "logs" / f"{method}-seed1.log").read_text()
        assert f"drago train smoke --method {method} --seed 1" in log and "(SLURM job " in log
    for name in ("report.html", "report.md", "transfers.csv", "transfers.md"):
        assert (out / "report" / name).is_file(), name
    # SLURM ran the same commands: the same logs as the local study, byte for byte.
    assert snapshot(out / RUN) == snapshot(reference / RUN)

    status = drago(*study_argv(out, "--status", methods=METHODS))
    print(status.stdout)
    assert status.returncode == 0 and "4 done, 0 running, 0 queued, 0 failed, 0 to do" in status.stdout
    # Again: nothing to submit; the report is written here.
    again = drago(*study_argv(out, methods=METHODS), timeout=120)
    assert again.returncode == 0, again.stderr
    assert "submitted job" not in again.stdout and "every job is finished: writing the report here" in again.stdout
    assert set(c.job_states()) == set(states)


def _stop_when(condition, timeout: float, what: str) -> None:
    wait_for(condition, timeout, what, interval=0.05)


@pytest.mark.slow
def test_a_cancelled_job_finishes_after_the_same_command_with_identical_logs(slurm_env: SlurmCluster, reference,
                                                                            tmp_path):
    c = slurm_env
    out = tmp_path / "cancelled"
    first = drago(*study_argv(out), timeout=180, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    assert "checked: the nodes see the study folder" in first.stdout
    assert first.stdout.count("submitted job ") == 3  # the run, its transfer, the report
    run_job, transfer_job = job_of(out, "continual seed1"), job_of(out, "continual seed1 room1to2-after2")
    resume = out / RUN / "checkpoints" / "resume.pt"
    # In the middle: once a periodic checkpoint has been written, while the run trains on.
    _stop_when(resume.exists, 120, "the run's first periodic checkpoint")
    c.run(["scancel", run_job])
    assert c.wait_job(run_job, ("CANCELLED",), timeout=60) == "CANCELLED"
    # Its transfer can never start: SLURM cancels it (--kill-on-invalid-dep), the report still runs.
    assert c.wait_job(transfer_job, ("CANCELLED",), timeout=60) == "CANCELLED"
    assert not (out / RUN / "summary.json").exists() or not json.loads(
        (out / RUN / "summary.json").read_text())["complete"]
    print("\nsqueue -t all after scancel:\n" + c.squeue("%.6i %.40j %.10T %.10M %R", all_states=True))
    status = drago(*study_argv(out, "--status"))
    print(status.stdout)
    row = next(line for line in status.stdout.splitlines() if line.split()[:3] == ["failed", "continual", "seed1"])
    assert f"job {run_job} CANCELLED; log: {out / 'logs' / 'continual-seed1.log'}; last error: " in row
    assert "not started: its run failed" in status.stdout

    again = drago(*study_argv(out, "--wait"), timeout=600, cwd=tmp_path)
    print(again.stdout + again.stderr)
    assert again.returncode == 0, again.stderr
    assert "runs:      0 to start, 1 to resume, 0 finished" in again.stdout
    assert again.stdout.count("submitted job ") == 3 and "study complete: 2 jobs run through SLURM" in again.stdout
    # Why each is submitted again: the run's job was cancelled (its log and last error line), its transfer never ran.
    assert f"again: continual seed1 (job {run_job} CANCELLED; log: {out / 'logs' / 'continual-seed1.log'}; " \
           "last error: " in again.stdout
    assert f"again: continual seed1 room1to2-after2 (job {transfer_job} never started" in again.stdout
    log = (out / "logs" / "continual-seed1.log").read_text()
    assert "drago: interrupted" in log and f"drago resume {out / RUN}" in log and "resumed at step" in log
    assert snapshot(out) == snapshot(reference)  # byte-identical train.csv and eval.csv, run and transfer
    for name in ("report.html", "report.md", "transfers.csv", "transfers.md"):
        assert (out / "report" / name).is_file(), name

    done = drago(*study_argv(out, "--status"))
    assert done.returncode == 0 and "2 done, 0 running, 0 queued, 0 failed, 0 to do" in done.stdout
    # Once more: nothing to submit; the report is written here.
    states = c.job_states()
    last = drago(*study_argv(out), timeout=120)
    assert last.returncode == 0, last.stderr
    assert "submitted job" not in last.stdout and "every job is finished: writing the report here" in last.stdout
    assert set(c.job_states()) == set(states)


@pytest.mark.slow
def test_a_second_command_while_the_jobs_are_queued_submits_nothing(slurm_env: SlurmCluster, tmp_path, capsys):
    c = slurm_env
    out = tmp_path / "held"
    argv = study_argv(out, "--jobs", "1", "--sbatch=--begin=now+1hour", methods=METHODS)
    try:
        first = drago(*argv, timeout=180, cwd=tmp_path)
        assert first.returncode == 0, first.stderr
        before = jobs_file(out)
        ids = sorted(before["jobs"], key=int)
        assert len(ids) == 5 and all(c.job_states()[i] == "PENDING" for i in ids)
        shown = c.run(["scontrol", "show", "job", before["latest"]["continual seed1 room1to2-after2"]]).stdout
        assert "singleton" in shown and "afterok:" in shown  # one lane (--jobs 1), after its run

        again = drago(*argv, timeout=120, cwd=tmp_path)
        print("\n" + again.stdout)
        assert again.returncode == 0, again.stderr
        assert "submitted job" not in again.stdout and "nothing new to submit" in again.stdout
        assert again.stdout.count("kept job ") == 5
        assert jobs_file(out) == before and sorted(c.job_states(), key=int)[-5:] == ids

        status = drago(*study_argv(out, "--status", methods=METHODS))
        assert "0 done, 0 running, 4 queued, 0 failed, 0 to do" in status.stdout
        assert "PENDING (BeginTime)" in status.stdout and "report:  job" in status.stdout
        # The local backend would race the queued jobs for their directories: refused.
        assert cli.main(["study", "smoke", "--methods", *METHODS, "--seeds", "1", "--out", str(out),
                         "--transfer-episodes", "1", *TINY]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("drago: error: SLURM jobs of this study are queued or running")
        assert len(err.splitlines()) == 1
    finally:
        c.cancel_all()


@pytest.mark.slow
def test_an_unknown_partition_is_slurms_one_line_error(slurm_env: SlurmCluster, tmp_path):
    proc = drago(*study_argv(tmp_path / "nope", "--partition", "nope"), timeout=120, cwd=tmp_path)
    assert proc.returncode == 2
    err = proc.stderr.strip()
    assert len(err.splitlines()) == 1 and err.startswith("drago: error: SLURM refused the study's jobs: ")
    assert "invalid partition" in err.lower()


def _private_mounts_work(folder: Path) -> bool:
    if os.geteuid() != 0 or not shutil.which("unshare"):
        return False
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs tmpfs {folder} && touch {folder}/x"],
                           capture_output=True, timeout=30)
    return probe.returncode == 0 and not (folder / "x").exists()


@pytest.mark.slow
def test_a_folder_the_nodes_cannot_see_is_refused(slurm_env: SlurmCluster, tmp_path):
    """The study command runs where the folder is a private tmpfs (its own mount namespace): the node, which sees
    the machine's own filesystem there, cannot find what the command wrote."""
    out = tmp_path / "private"
    out.mkdir()
    if not _private_mounts_work(out):
        pytest.skip("needs root and `unshare -m` to give the study command a folder the node does not see")
    before = set(slurm_env.job_states())
    command = " ".join(["mount -t tmpfs tmpfs", str(out), "&&", "exec", sys.executable, "-m", "drago",
                        *[f"'{a}'" for a in study_argv(out)]])
    proc = subprocess.run(["unshare", "-m", "sh", "-c", command], capture_output=True, text=True, timeout=180,
                          cwd=tmp_path)
    print("\n" + proc.stdout + proc.stderr)
    assert proc.returncode == 2
    err = proc.stderr.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"drago: error: the SLURM nodes cannot use the study "
                                                         f"folder {out}")
    assert "put --out on a filesystem the nodes share" in err
    assert not list(out.iterdir())  # nothing reached the node's view of the folder
    new = set(slurm_env.job_states()) - before
    assert len(new) == 1 and slurm_env.squeue("%j", jobs=list(new), all_states=True) == "drago-check-folder"


@pytest.mark.experiment
def test_a_job_stopped_by_its_time_limit_is_requeued_and_finishes_identically(slurm_env: SlurmCluster, tmp_path):
    """The run trains for longer than the job's time limit: SLURM signals the job before the limit, the job stops
    drago and requeues itself (SLURM holds a requeued job for about two minutes), and the requeued job resumes.
    The same command, run again meanwhile, keeps the job and follows it to the end."""
    c = slurm_env
    # A two-minute limit: SLURM signals 30 s before it, at 60 to 90 s (it checks limits every 30 s). The run takes
    # about 100 s on a 2-core CPU, so the first attempt is always stopped, and the requeued one usually finishes (on a
    # busy machine it may take a third; each requeue waits about 2.5 minutes in the queue).
    settings = [*TINY, "train.steps_per_task=8500", "train.checkpoint_freq=500"]
    out = tmp_path / "timed"
    first = drago(*study_argv(out, "--time", "2", settings=settings), timeout=180, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    run_job = job_of(out, "continual seed1")
    log = out / "logs" / "continual-seed1.log"
    wait_for(lambda: log.exists() and "requeued, it continues from the last checkpoint" in log.read_text(), 240,
             "the job to be stopped near its time limit and requeued", c.log_tail)
    shown = c.run(["scontrol", "show", "job", run_job]).stdout
    print("\n" + shown)
    assert "Restarts=1" in shown or "Requeue=1" in shown
    reference = reference_study(tmp_path / "reference", settings)  # meanwhile, the uninterrupted study
    again = drago(*study_argv(out, "--time", "2", "--wait", settings=settings), timeout=900, cwd=tmp_path)
    print(again.stdout + again.stderr)
    assert again.returncode == 0, again.stderr
    assert f"kept job {run_job}" in again.stdout and "study complete" in again.stdout
    text = log.read_text()
    assert f"drago resume {out / RUN}" in text and "resumed at step" in text
    assert c.job_states()[run_job] == "COMPLETED"
    assert snapshot(out) == snapshot(reference)
