"""Wall time of every preset's smoke path for each agent kind: ``drago train PRESET --smoke agent.kind=KIND``.

A smoke path runs a preset's domain, tasks, agent kind and method at the smoke preset's budgets and sizes, to
check an installation or a change end to end. Each command runs alone, one after the other, in a fresh process
(its import time included); read the machine's load before comparing figures.

    cd benchmarks && ../.venv/bin/python smoke_paths.py [--presets P ...] [--kinds K ...] [--out CSV]
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from drago.agent.protocol import agent_kinds
from drago.config import available_presets

import drago.agent.factory  # noqa: F401 - registers the built-in agent kinds


def smoke_path_seconds(preset: str, kind: str, folder: Path) -> tuple[float, int]:
    """(wall seconds, exit code) of one smoke path."""
    command = [sys.executable, "-m", "drago", "train", preset, "--smoke", f"agent.kind={kind}", "--no-progress",
               "--out", str(folder / f"{preset}-{kind}")]
    started = time.perf_counter()
    code = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}).returncode
    return time.perf_counter() - started, code


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=[p for p in available_presets() if p != "smoke"])
    parser.add_argument("--kinds", nargs="+", default=list(agent_kinds()))
    parser.add_argument("--out", type=Path, default=None, help="also write the rows to this CSV")
    args = parser.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for preset in args.presets:
            for kind in args.kinds:
                seconds, code = smoke_path_seconds(preset, kind, Path(tmp))
                rows.append({"preset": preset, "agent_kind": kind, "wall_s": round(seconds, 1), "exit_code": code})
                print(f"{preset:<20} {kind:<8} {seconds:6.1f} s" + ("" if code == 0 else f"  (exit code {code})"),
                      flush=True)
    if args.out is not None:
        with args.out.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return 0 if all(r["exit_code"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
