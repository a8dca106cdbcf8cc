"""Wall time of every preset's smoke path for each agent kind: ``drago train PRESET --smoke agent.kind=KIND``.

A smoke path runs a preset's domain, tasks, agent kind and method at the smoke preset's budgets and sizes, to
check an installation or a change end to end. Each command runs alone, one after the other, in a fresh process
(its import time included), with one torch thread. Wall time depends on what else the machine runs; the
command's CPU seconds (user and system, from the OS's accounting of the finished child) hardly do, and on an
idle machine a one-thread command's wall time is about its CPU time. Read the printed load before comparing.

    cd benchmarks && ../.venv/bin/python smoke_paths.py [--presets P ...] [--kinds K ...] [--out CSV]
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from drago.agent.protocol import agent_kinds
from drago.config import available_presets

import drago.agent.factory  # noqa: F401 - registers the built-in agent kinds


def children_cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def smoke_path_seconds(preset: str, kind: str, folder: Path) -> tuple[float, float, int]:
    """(wall seconds, CPU seconds, exit code) of one smoke path."""
    command = [sys.executable, "-m", "drago", "train", preset, "--smoke", f"agent.kind={kind}", "--no-progress",
               "train.threads=1", "--out", str(folder / f"{preset}-{kind}")]
    cpu_before, started = children_cpu_seconds(), time.perf_counter()
    code = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}).returncode
    return time.perf_counter() - started, children_cpu_seconds() - cpu_before, code


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=[p for p in available_presets() if p != "smoke"])
    parser.add_argument("--kinds", nargs="+", default=list(agent_kinds()))
    parser.add_argument("--out", type=Path, default=None, help="also write the rows to this CSV")
    args = parser.parse_args()
    print(f"{cpu_model()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f} before the first command")
    print(f"{'preset':<20} {'kind':<8} {'wall s':>7} {'CPU s':>7}  load")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for preset in args.presets:
            for kind in args.kinds:
                wall, cpu, code = smoke_path_seconds(preset, kind, Path(tmp))
                load = os.getloadavg()[0]
                rows.append({"preset": preset, "agent_kind": kind, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
                             "load_1min": round(load, 1), "exit_code": code})
                print(f"{preset:<20} {kind:<8} {wall:7.1f} {cpu:7.1f}  {load:4.1f}"
                      + ("" if code == 0 else f"  (exit code {code})"), flush=True)
    if args.out is not None:
        with args.out.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return 0 if all(r["exit_code"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
