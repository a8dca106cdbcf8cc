"""The one-node SLURM test cluster (tests/slurm_cluster.py) against a real slurmctld / slurmd: comes up idle on
127.0.0.1, runs batch jobs, lists and cancels them, reports failed and cancelled jobs in squeue, and runs a submitit
job. Skipped with the reason where SLURM is not installed or cannot start (scripts/setup.sh installs it)."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest

# The fixtures slurm_cluster (session) and slurm_env (per test) come from tests/slurm_cluster.py, a plugin module
# (registered for assertion rewriting before the import below, as pytest wants of plugins).
pytest_plugins = ("slurm_cluster",)
pytest.register_assert_rewrite("slurm_cluster")
from slurm_cluster import SlurmCluster, SlurmUnavailable, _unavailable, start_slurm_cluster, wait_for  # noqa: E402

# Every test here starts a SLURM cluster.
pytestmark = pytest.mark.slow


def _listening(port: int) -> set[str]:
    """Local addresses with a listening TCP socket on ``port`` (from /proc/net/tcp and tcp6)."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            addr, hex_port = fields[1].rsplit(":", 1)
            if fields[3] != "0A" or int(hex_port, 16) != port:  # 0A: LISTEN
                continue
            if len(addr) == 8:
                found.add(socket.inet_ntop(socket.AF_INET, bytes.fromhex(addr)[::-1]))
            else:  # IPv6: four little-endian 32-bit words
                raw = b"".join(bytes.fromhex(addr[i:i + 8])[::-1] for i in range(0, 32, 8))
                found.add(socket.inet_ntop(socket.AF_INET6, raw))
    return found


def test_cluster_comes_up_idle_on_loopback(slurm_cluster: SlurmCluster):
    c = slurm_cluster
    print(f"\nstartup: {c.startup_s:.1f} s; SLURM_CONF={c.conf}; ports {c.ports}")
    print("sinfo:\n" + c.sinfo())
    print("squeue:\n" + c.run(["squeue"]).stdout)
    assert c.sinfo("%P %T %N") == f"{c.partition}* idle {c.node}"
    assert c.env["SLURM_CONF"] == str(c.conf)
    for name, port in c.ports.items():
        addresses = _listening(port)
        print(f"{name} listens on {sorted(addresses)} port {port}")
        assert addresses == {"127.0.0.1"}, f"{name} listens on {addresses}"
    assert all(p.poll() is None for p in c.processes.values())


def test_sbatch_wrap_runs_and_writes_a_file(slurm_cluster: SlurmCluster, tmp_path: Path):
    out = tmp_path / "job.txt"
    job = slurm_cluster.sbatch("-J", "tiny", "-o", str(tmp_path / "slurm-%j.out"), "--chdir", str(tmp_path),
                               "--wrap", f'echo "$SLURM_JOB_ID $SLURMD_NODENAME" > {out}')
    assert slurm_cluster.wait_job(job, timeout=30) == "COMPLETED"
    assert out.read_text().split() == [job, slurm_cluster.node]
    # Finished jobs stay in squeue (MinJobAge): a study reads its jobs' end states there, no sacct needed.
    print("\n" + slurm_cluster.squeue("%i %j %T %r", all_states=True, jobs=[job]))
    assert slurm_cluster.job_states()[job] == "COMPLETED"


def test_srun_runs_a_step_on_the_node(slurm_cluster: SlurmCluster):
    out = slurm_cluster.run(["srun", "-n", "1", "-t", "1", "sh", "-c", "echo $SLURM_JOB_ID $SLURMD_NODENAME"]).stdout
    job_id, node = out.split()
    assert node == slurm_cluster.node
    assert slurm_cluster.wait_job(job_id, timeout=30) == "COMPLETED"


def test_failed_job_shows_as_failed(slurm_cluster: SlurmCluster, tmp_path: Path):
    job = slurm_cluster.sbatch("-o", str(tmp_path / "slurm-%j.out"), "--wrap", "exit 3")
    assert slurm_cluster.wait_job(job, ("FAILED",), timeout=30) == "FAILED"
    assert "ExitCode=3:0" in slurm_cluster.run(["scontrol", "show", "job", job]).stdout


def test_squeue_lists_pending_and_running_jobs_and_scancel_removes_them(slurm_cluster: SlurmCluster, tmp_path: Path):
    c = slurm_cluster
    pid_file = tmp_path / "sleep.pid"
    held = c.sbatch("-J", "held", "--begin=now+1hour", "-o", "/dev/null", "--wrap", "true")
    running = c.sbatch("-J", "sleeper", "-o", str(tmp_path / "slurm-%j.out"),
                       "--wrap", f"echo $$ > {pid_file}; exec sleep 300")
    c.wait_job(running, ("RUNNING",), timeout=30)
    wait_for(lambda: pid_file.exists() and pid_file.read_text().strip(), 15, "the job to write its pid")
    listed = c.squeue()
    print("\nsqueue:\n" + listed)
    states = c.job_states()
    assert states[held] == "PENDING" and states[running] == "RUNNING"
    assert f"{held} held PENDING BeginTime" in listed

    c.run(["scancel", held, running])
    assert c.wait_job(held, ("CANCELLED",), timeout=30) == "CANCELLED"
    assert c.wait_job(running, ("CANCELLED",), timeout=30) == "CANCELLED"
    assert c.squeue("%i").split() == []
    pid = int(pid_file.read_text())
    wait_for(lambda: not Path(f"/proc/{pid}").exists(), 20, f"the cancelled job's process {pid} to end")
    print("squeue -t all:\n" + c.squeue(all_states=True))


@pytest.mark.experiment
def test_time_limit_kills_the_job(slurm_cluster: SlurmCluster, tmp_path: Path):
    # --time=1 is SLURM's shortest limit (a minute); slurmctld checks limits every 30 s: 60 to 100 s in all.
    start = time.monotonic()
    job = slurm_cluster.sbatch("--time=1", "-o", str(tmp_path / "slurm-%j.out"), "--wrap", "sleep 600")
    assert slurm_cluster.wait_job(job, ("TIMEOUT",), timeout=150) == "TIMEOUT"
    print(f"\njob {job} ended TIMEOUT after {time.monotonic() - start:.0f} s")


def test_submitit_returns_a_function_result(slurm_env: SlurmCluster, tmp_path: Path, monkeypatch):
    # Imported as drago imports it: submitit's own logging set-up would close pytest's captured streams.
    monkeypatch.setenv("SUBMITIT_LOG_LEVEL", "NOCONFIG")
    submitit = pytest.importorskip("submitit")

    def work(a: int, b: int) -> tuple[int, str, str]:  # nested: cloudpickle sends it by value
        import os

        return a * b, os.environ["SLURM_JOB_ID"], os.environ["SLURMD_NODENAME"]

    executor = submitit.AutoExecutor(folder=tmp_path / "submitit", cluster="slurm")
    executor.update_parameters(slurm_partition=slurm_env.partition, timeout_min=5, nodes=1, tasks_per_node=1,
                               cpus_per_task=1, name="drago-submitit-check")
    job = executor.submit(work, 6, 7)
    # Without slurmdbd (no sacct) submitit's states read UNKNOWN: done() sees the result file; squeue has the state.
    wait_for(job.done, 60, f"submitit job {job.job_id}",
             lambda: f"squeue: {slurm_env.squeue(all_states=True)}\nstdout: {job.stdout()}\nstderr: {job.stderr()}")
    assert job.result() == (42, job.job_id, slurm_env.node)
    assert slurm_env.wait_job(job.job_id, timeout=30) == "COMPLETED"


def test_a_second_cluster_starts_alongside_and_leaves_nothing_behind(slurm_cluster: SlurmCluster, tmp_path: Path):
    t0 = time.monotonic()
    try:
        with start_slurm_cluster(tmp_path / "second") as other:
            assert set(other.ports.values()).isdisjoint(slurm_cluster.ports.values())
            assert other.munge_socket != slurm_cluster.munge_socket
            job = other.sbatch("-J", "second-cluster-job", "-o", "/dev/null", "--wrap", "true")
            assert other.wait_job(job, timeout=30) == "COMPLETED"
            assert "second-cluster-job" not in slurm_cluster.squeue("%j", all_states=True).split()
    except SlurmUnavailable as e:
        _unavailable(str(e))
    print(f"\nsecond cluster: up in {other.startup_s:.1f} s, up and down in {time.monotonic() - t0:.1f} s")
    assert all(p.poll() is not None for p in other.processes.values())
    assert not other.munge_socket.parent.exists()
    for port in other.ports.values():
        with socket.socket() as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("127.0.0.1", port))  # free again
    # The first cluster did not notice.
    assert slurm_cluster.sinfo("%T") == "idle"
    assert (tmp_path / "second" / "log" / "slurmctld.log").exists()  # logs stay for inspection
