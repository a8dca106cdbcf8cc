"""A real one-node SLURM cluster on this machine, for tests: pytest fixtures and the context manager behind them.

``start_slurm_cluster(folder)`` starts a private munged (its own key and socket), slurmctld and slurmd from Debian's
``slurm-wlm`` and ``munge`` packages (scripts/setup.sh installs them where it can) with a generated slurm.conf, waits
until the node is up, and stops everything again on exit. Nothing outside ``folder`` is written except the munge
socket's folder (``/tmp/drago-munge-*``, removed on exit): no /etc, /run or /var file is read or changed, so any number
of sessions, one after the other or at the same time, can each start their own cluster.

Network: every daemon listens on 127.0.0.1 only, on ports found free at start. SLURM binds to the address its host
name resolves to when asked to (``CommunicationParameters=NoInAddrAny,NoCtldInAddrAny``); the daemons therefore run in
a UTS namespace of their own whose host name is ``localhost`` (``unshare --uts``, root only), which also makes the
node's name ``localhost``. Where no UTS namespace can be made, the machine's own host name must resolve to a loopback
address, or the cluster is not started.

No slurmdbd: there is no ``sacct``, so job states come from ``squeue -t all`` (finished jobs stay listed for
``MinJobAge`` = 3600 s).

Fixtures (a test module lists this module in ``pytest_plugins = ("slurm_cluster",)``, as tests/test_slurm_cluster.py
does, or imports them):

* ``slurm_cluster`` (session): the running ``SlurmCluster``; its ``env`` is what client commands need.
* ``slurm_env`` (function): the same cluster, with ``SLURM_CONF`` set in ``os.environ`` for the test (and any
  inherited ``SLURM_*`` / ``SBATCH_*`` variables removed), for code that calls ``sbatch`` itself, such as submitit.

Where the binaries are missing, the user is not root or the cluster does not come up, the fixtures skip the test with
the reason and the last lines of the daemons' logs; with ``DRAGO_REQUIRE_SLURM=1`` in the environment they fail instead.
The logs stay under the pytest temporary folder for inspection.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from helpers import wait_for

DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("munge", "unmunge", "sbatch", "squeue", "scancel", "sinfo", "scontrol", "srun")
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 15.0
PARTITION = "debug"
NODE = "localhost"
# Client settings inherited from a surrounding job or a user's shell would change what the commands do or print.
_CLIENT_ENV_PREFIXES = ("SLURM_", "SBATCH_", "SALLOC_", "SRUN_", "SQUEUE_", "SINFO_", "SCANCEL_", "SCONTROL_")

_LISTENING_CLIENTS = ("srun", "salloc", "sattach")
# The daemons' launcher: in a new UTS namespace (unshare --uts), set the host name to localhost, then exec the daemon.
_UTS_SHIM = "import os, socket, sys; socket.sethostname(sys.argv[1]); os.execvp(sys.argv[2], sys.argv[2:])"


def _which(name: str) -> str | None:
    """The program's path; daemons are looked for in the sbin folders too (often not on a PATH)."""
    return shutil.which(name) or shutil.which(name, path="/usr/local/sbin:/usr/sbin:/sbin")


class SlurmUnavailable(RuntimeError):
    """The cluster cannot be started here; the message says why."""


@dataclass
class SlurmCluster:
    """A running one-node cluster: its files, the environment for client commands and a few helpers."""

    root: Path
    conf: Path
    env: dict[str, str]
    logs: dict[str, Path]
    ports: dict[str, int]
    munge_socket: Path
    partition: str = PARTITION
    node: str = NODE
    startup_s: float = 0.0
    processes: dict[str, subprocess.Popen] = field(default_factory=dict, repr=False)
    # Prefix for commands that listen (srun, salloc: their I/O ports bind to the host name's address), so that they
    # too run where the host name is localhost; empty where the machine's host name is loopback already.
    launcher: list[str] = field(default_factory=list, repr=False)

    def run(self, cmd: str | Sequence[str], *, timeout: float = 30.0, check: bool = True,
            cwd: str | os.PathLike | None = None) -> subprocess.CompletedProcess:
        """Runs a client command (a list, or a string split like a shell would) against this cluster."""
        args = shlex.split(cmd) if isinstance(cmd, str) else [str(a) for a in cmd]
        if args and os.path.basename(args[0]) in _LISTENING_CLIENTS:
            args = [*self.launcher, *args]
        proc = subprocess.run(args, check=False, env=self.env, cwd=cwd, capture_output=True, text=True, timeout=timeout)
        if check and proc.returncode != 0:
            raise RuntimeError(f"{shlex.join(args)} exited with {proc.returncode}: {proc.stderr.strip()}")
        return proc

    def sinfo(self, fmt: str = "%P %a %D %T %N") -> str:
        return self.run(["sinfo", "-h", "-o", fmt]).stdout.strip()

    def squeue(self, fmt: str = "%i %j %T %r", *, all_states: bool = False, jobs: Sequence[str] = ()) -> str:
        args = ["squeue", "-h", "-o", fmt]
        if all_states:
            args += ["-t", "all"]
        if jobs:
            args += ["-j", ",".join(jobs)]
        return self.run(args).stdout.strip()

    def job_states(self) -> dict[str, str]:
        """Job id -> state of every job slurmctld still knows (finished ones for MinJobAge seconds)."""
        return dict(line.split() for line in self.squeue("%i %T", all_states=True).splitlines() if line.strip())

    def sbatch(self, *args: str, cwd: str | os.PathLike | None = None) -> str:
        """Submits a batch job (sbatch arguments, e.g. "--wrap", "true") and returns its id."""
        out = self.run(["sbatch", "--parsable", *args], cwd=cwd).stdout.strip()
        return out.split(";")[0]

    def wait_job(self, job_id: str, states: Sequence[str] = ("COMPLETED",), timeout: float = 30.0) -> str:
        """Waits until the job is in one of ``states`` (or in none of the active ones) and returns its state."""
        active = {"PENDING", "CONFIGURING", "RUNNING", "COMPLETING", "SUSPENDED", "REQUEUED", "RESIZING"}
        seen: list[str] = []

        def settled() -> bool:
            state = self.job_states().get(job_id, "GONE")
            if not seen or seen[-1] != state:
                seen.append(state)
            return state in states or state not in active

        wait_for(settled, timeout, f"job {job_id} to reach {'/'.join(states)}", self.log_tail)
        return seen[-1]

    def cancel_all(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Cancels every pending or running job and waits (bounded) until none is left active."""
        ids = self.squeue("%i").split()
        if not ids:
            return
        self.run(["scancel", *ids], check=False)
        with contextlib.suppress(TimeoutError, RuntimeError, subprocess.TimeoutExpired):
            wait_for(lambda: not self.squeue("%i").split(), timeout, "cancelled jobs to leave the queue")

    def log_tail(self, lines: int = 15) -> str:
        return _log_tail(self.logs, lines)


def _log_tail(logs: dict[str, Path], lines: int) -> str:
    parts = []
    for path in logs.values():
        stderr = path.with_suffix(".stderr")
        if not (path.exists() and path.stat().st_size) and stderr.exists():
            path = stderr
        try:
            text = path.read_text(errors="replace").splitlines()[-lines:]
        except OSError:
            continue
        if text:
            parts.append(f"--- last lines of {path} ---\n" + "\n".join(text))
    return "\n".join(parts)


def _client_env(conf: Path | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(_CLIENT_ENV_PREFIXES)}
    if conf is not None:
        env["SLURM_CONF"] = str(conf)
    return env


def _free_ports(count: int) -> list[int]:
    """Ports free on 127.0.0.1 now (all held open together while choosing, so they differ)."""
    socks = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _is_loopback(name: str) -> bool:
    try:
        addrs = {info[4][0] for info in socket.getaddrinfo(name, None, socket.AF_INET)}
    except OSError:
        return False
    return bool(addrs) and all(a.startswith("127.") for a in addrs)


def _uts_namespace_works() -> bool:
    if not shutil.which("unshare"):
        return False
    try:
        proc = subprocess.run(["unshare", "--uts", sys.executable, "-c", _UTS_SHIM, NODE, "true"],
                              capture_output=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0


def _node_hardware() -> str:
    """The node line's hardware fields, as slurmd itself measures them (``slurmd -C``), else from the OS."""
    try:
        out = subprocess.run([_which("slurmd") or "slurmd", "-C"], check=False, capture_output=True, text=True,
                             timeout=30, env=_client_env()).stdout
    except (OSError, subprocess.TimeoutExpired):
        out = ""
    fields = dict(re.findall(r"(\w+)=(\S+)", out.splitlines()[0])) if out.strip() else {}
    keys = ("CPUs", "Boards", "SocketsPerBoard", "CoresPerSocket", "ThreadsPerCore", "RealMemory")
    if all(k in fields for k in keys):
        return " ".join(f"{k}={fields[k]}" for k in keys)
    mem_kib = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
                   if line.startswith("MemTotal:"))
    return f"CPUs={os.cpu_count() or 1} RealMemory={mem_kib // 1024}"


def write_slurm_conf(path: Path, *, root: Path, spool: Path, controller: str, ctld_port: int, slurmd_port: int,
                     munge_socket: Path, hardware: str) -> None:
    """A one-node cluster on 127.0.0.1: no cgroups, no accounting database, state and logs under ``root``.

    ``spool`` holds slurmd's step sockets, whose paths must stay under the 108 bytes of a Unix socket name: a
    short folder under /tmp, not one deep in pytest's (or pytest-xdist's) temporary tree."""
    path.write_text(f"""\
# Generated by tests/slurm_cluster.py: a one-node SLURM cluster on 127.0.0.1 for the test suite.
ClusterName=dragotest
SlurmctldHost={controller}(127.0.0.1)
SlurmctldPort={ctld_port}
SlurmdPort={slurmd_port}
# Listen on the address the host name resolves to (127.0.0.1), not on every address.
CommunicationParameters=NoInAddrAny,NoCtldInAddrAny
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={munge_socket}
SlurmUser=root
SlurmdUser=root
StateSaveLocation={root}/state
SlurmdSpoolDir={spool}
SlurmctldPidFile={root}/run/slurmctld.pid
SlurmdPidFile={root}/run/slurmd.pid
SlurmctldLogFile={root}/log/slurmctld.log
SlurmdLogFile={root}/log/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SwitchType=switch/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
SlurmctldTimeout=30
SlurmdTimeout=30
MessageTimeout=10
InactiveLimit=0
KillWait=5
OverTimeLimit=0
# Finished jobs stay in `squeue -t all` for an hour: a slow test still sees every job of its study.
MinJobAge=3600
MailProg=/bin/true
NodeName={NODE} NodeAddr=127.0.0.1 {hardware} State=UNKNOWN
PartitionName={PARTITION} Nodes={NODE} Default=YES MaxTime=INFINITE State=UP
""")


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the test process dies, so no daemon outlives a killed session."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _stop(proc: subprocess.Popen, timeout: float = STOP_TIMEOUT_S) -> None:
    """SIGTERM to the daemon's process group (it leads its own session), then SIGKILL after ``timeout``."""
    if proc.poll() is not None:
        return
    for sig, wait in ((signal.SIGTERM, timeout), (signal.SIGKILL, 5.0)):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout=wait)
            break
        except subprocess.TimeoutExpired:
            continue
    # Anything of ours still in the group (a slurmstepd that outlived its slurmd).
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)


@contextlib.contextmanager
def start_slurm_cluster(root: Path, timeout: float = START_TIMEOUT_S) -> Iterator[SlurmCluster]:
    """Starts munged, slurmctld and slurmd for a one-node cluster under ``root``; stops them on exit.

    Raises SlurmUnavailable (with the reason and the logs' last lines) when the cluster cannot come up.
    """
    t0 = time.monotonic()
    programs = {b: _which(b) for b in DAEMONS + CLIENTS}
    missing = [b for b, path in programs.items() if not path]
    if missing:
        raise SlurmUnavailable(f"SLURM / munge programs not found: {', '.join(missing)} (scripts/setup.sh installs "
                               "Debian's slurm-wlm and munge with apt-get, as root or with password-less sudo)")
    if os.geteuid() != 0:
        raise SlurmUnavailable("the test cluster runs its daemons as root (SlurmUser=root); not root here")
    if _uts_namespace_works():
        controller, launcher, slurmd_extra = NODE, ["unshare", "--uts", sys.executable, "-c", _UTS_SHIM, NODE], []
        if not _is_loopback(NODE):
            raise SlurmUnavailable(f"'{NODE}' does not resolve to a loopback address here")
    else:
        controller, launcher, slurmd_extra = socket.gethostname().split(".")[0], [], ["-N", NODE]
        if not _is_loopback(controller):
            raise SlurmUnavailable(f"no UTS namespace (unshare --uts) and the host name '{controller}' does not "
                                   "resolve to 127.0.0.1: the daemons would not listen on loopback only")

    root = Path(root)
    for sub in ("munge", "state", "log", "run"):
        (root / sub).mkdir(mode=0o700, parents=True, exist_ok=True)
    # Sockets live in a short folder of their own: munged wants every folder above its socket searchable by all
    # (pytest's own temporary folder is 0700), and a Unix socket's path has at most 108 bytes (slurmd's spool).
    sock_dir = Path(tempfile.mkdtemp(prefix="drago-munge-", dir="/tmp" if os.path.isdir("/tmp") else None))
    sock_dir.chmod(0o711)
    munge_socket = sock_dir / "munge.socket"
    spool = sock_dir / "spool"
    spool.mkdir(mode=0o700)
    # munged -F logs to its stderr; slurmctld and slurmd write their log files (and, with -D, the same to stderr:
    # <name>.stderr, which log_tail shows only where the log file is missing, e.g. after a bad slurm.conf).
    logs = {"munged": root / "log" / "munged.log", "slurmctld": root / "log" / "slurmctld.log",
            "slurmd": root / "log" / "slurmd.log"}
    conf = root / "slurm.conf"
    cluster = SlurmCluster(root=root, conf=conf, env=_client_env(conf), logs=logs, munge_socket=munge_socket,
                           ports={}, launcher=launcher)

    def spawn(name: str, args: list[str]) -> None:
        out = open(logs[name] if name == "munged" else root / "log" / f"{name}.stderr", "ab")  # noqa: SIM115
        try:
            cluster.processes[name] = subprocess.Popen(args, env=cluster.env, stdin=subprocess.DEVNULL, stdout=out,
                                                       stderr=subprocess.STDOUT, start_new_session=True,
                                                       preexec_fn=_die_with_parent)
        finally:
            out.close()

    def check_alive() -> None:
        for name, proc in cluster.processes.items():
            if proc.poll() is not None:
                raise SlurmUnavailable(f"{name} exited with {proc.returncode} while the cluster started\n"
                                       f"{cluster.log_tail()}")

    try:
        key = root / "munge" / "munge.key"
        fd = os.open(key, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(os.urandom(128))
        ctld_port, slurmd_port = _free_ports(2)
        cluster.ports.update(slurmctld=ctld_port, slurmd=slurmd_port)
        write_slurm_conf(conf, root=root, spool=spool, controller=controller, ctld_port=ctld_port,
                         slurmd_port=slurmd_port,
                         munge_socket=munge_socket, hardware=_node_hardware())

        m = root / "munge"
        # -F: foreground, so munged's log is its stderr (munged.log) and its pid is the child's.
        spawn("munged", [programs["munged"], "-F", f"--key-file={key}", f"--socket={munge_socket}",
                         f"--pid-file={m / 'munged.pid'}", f"--seed-file={m / 'munged.seed'}",
                         "--origin=127.0.0.1"])

        def munge_works() -> bool:
            check_alive()
            if not munge_socket.exists():
                return False
            cred = subprocess.run([programs["munge"], "-n", "-S", str(munge_socket)], check=False,
                                  capture_output=True, timeout=10)
            return cred.returncode == 0 and subprocess.run(
                [programs["unmunge"], "-S", str(munge_socket)], input=cred.stdout, check=False, capture_output=True,
                timeout=10).returncode == 0

        wait_for(munge_works, 20, "munged to answer on its socket", cluster.log_tail, interval=0.2)

        spawn("slurmctld", [*launcher, programs["slurmctld"], "-D", "-f", str(conf)])
        spawn("slurmd", [*launcher, programs["slurmd"], "-D", "-f", str(conf), *slurmd_extra])

        states: list[str] = []

        def node_up() -> bool:
            check_alive()
            try:
                proc = subprocess.run([programs["sinfo"], "-h", "-o", "%T"], check=False, env=cluster.env,
                                      capture_output=True, text=True, timeout=15)
            except subprocess.TimeoutExpired:
                return False
            state = proc.stdout.strip() if proc.returncode == 0 else "(no answer)"
            if not states or states[-1] != state:
                states.append(state)
            if state.rstrip("*~#!%$@^-") in {"drained", "draining", "inval", "fail"}:
                reason = cluster.run(["sinfo", "-h", "-R", "-o", "%E"], check=False).stdout.strip()
                raise SlurmUnavailable(f"node went {state} ({reason})\n{cluster.log_tail()}")
            # A cluster restarted over its saved state comes back with the jobs it had: its node is up but busy.
            return state in {"idle", "mixed", "allocated", "completing"}

        wait_for(node_up, max(5.0, timeout - (time.monotonic() - t0)), "the node to be up",
                 lambda: f"sinfo states seen: {' -> '.join(states)}\n{cluster.log_tail()}")
        cluster.startup_s = time.monotonic() - t0
    except (TimeoutError, OSError, subprocess.SubprocessError) as e:
        _shutdown(cluster, sock_dir)
        raise SlurmUnavailable(f"{type(e).__name__}: {e}") from None
    except BaseException:
        _shutdown(cluster, sock_dir)
        raise
    try:
        yield cluster
    finally:
        _shutdown(cluster, sock_dir)


def _shutdown(cluster: SlurmCluster, sock_dir: Path) -> None:
    """Cancels what is left in the queue, stops slurmd, slurmctld and munged, removes the sockets' folder."""
    with contextlib.suppress(Exception):
        if cluster.processes.get("slurmctld") and cluster.processes["slurmctld"].poll() is None:
            cluster.cancel_all()
    for name in ("slurmd", "slurmctld", "munged"):
        if name in cluster.processes:
            _stop(cluster.processes[name])
    shutil.rmtree(sock_dir, ignore_errors=True)


def _unavailable(reason: str) -> None:
    if os.environ.get("DRAGO_REQUIRE_SLURM") == "1":
        pytest.fail(f"SLURM test cluster unavailable (DRAGO_REQUIRE_SLURM=1): {reason}", pytrace=False)
    pytest.skip(f"SLURM test cluster unavailable: {reason}")


@pytest.fixture(scope="session")
def slurm_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SlurmCluster]:
    """A one-node SLURM cluster on 127.0.0.1 for the whole session (skips the test where it cannot start)."""
    root = tmp_path_factory.mktemp("slurm")
    try:
        with start_slurm_cluster(root) as cluster:
            print(f"\nSLURM test cluster up in {cluster.startup_s:.1f} s: SLURM_CONF={cluster.conf}, "
                  f"ports {cluster.ports}")
            yield cluster
    except SlurmUnavailable as e:
        _unavailable(str(e))


@pytest.fixture
def slurm_env(slurm_cluster: SlurmCluster, monkeypatch: pytest.MonkeyPatch) -> SlurmCluster:
    """The session's cluster, with SLURM_CONF in os.environ for this test (for sbatch called by other code)."""
    for k in list(os.environ):
        if k.startswith(_CLIENT_ENV_PREFIXES):
            monkeypatch.delenv(k)
    monkeypatch.setenv("SLURM_CONF", str(slurm_cluster.conf))
    return slurm_cluster
