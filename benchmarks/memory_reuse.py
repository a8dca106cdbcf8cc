"""Page faults of a repeated large allocation, with the allocator as runs set it and with glibc's defaults.

Runs keep freed memory for reuse (``drago.training.resources.keep_freed_memory``; docs: Speed and precision,
"Runs keep freed memory"): a 64 MiB tensor allocated again and again then reuses the same pages, where glibc's
defaults map it afresh each time and the kernel faults in each of its 16,384 pages again. Each setting runs in
a process of its own, since the setting is process-wide and cannot be undone.

    .venv/bin/python benchmarks/memory_reuse.py [--rounds 12] [--mib 64]

Not part of the test suite (the tests check that freed memory stays with the process). It prints the date,
the commit and the CPU, then the minor page faults per allocation once the heap has settled (the last four
rounds), for each setting. Linux with glibc only.
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys

from zero_shot_ceiling import commit  # noqa: E402  (benchmarks/ is the script's folder)

from drago.training.records import cpu_model

CHILD = """
import resource, sys, torch
from drago.training.resources import keep_freed_memory
print(keep_freed_memory())
for _ in range({rounds}):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    torch.ones({numel}).sum()  # allocated, touched, freed at once
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def faults(keep: bool, rounds: int, mib: int) -> tuple[bool, list[int]]:
    """(whether the allocator was changed, the page faults of each round) in a fresh process."""
    env = {**os.environ, "DRAGO_KEEP_FREED_MEMORY": "1" if keep else "0", "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", CHILD.format(rounds=rounds, numel=mib * 2**20 // 4)], env=env,
                         capture_output=True, text=True, check=True).stdout.split()
    return out[0] == "True", [int(n) for n in out[1:]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=12,
                        help="allocations per process (the first few settle the heap)")
    parser.add_argument("--mib", type=int, default=64, help="size of the tensor allocated each round")
    args = parser.parse_args()
    if not sys.platform.startswith("linux"):
        sys.exit("memory_reuse.py: Linux only (glibc's allocator and Linux's page-fault counts)")
    print(f"{datetime.date.today()}  commit {commit()}  {cpu_model()}")
    print(f"{args.mib} MiB ({args.mib * 2**20 // os.sysconf('SC_PAGE_SIZE'):,} pages) allocated {args.rounds} times")
    settings = ((True, "kept for reuse (runs' default)"), (False, "glibc's defaults (DRAGO_KEEP_FREED_MEMORY=0)"))
    for keep, label in settings:
        applied, counts = faults(keep, args.rounds, args.mib)
        late = counts[-4:]
        note = "" if applied == keep else "  (the setting did not apply: not glibc?)"
        print(f"  {label:46s} page faults per allocation, last {len(late)} rounds: "
              f"{', '.join(f'{n:,}' for n in late)}{note}")


if __name__ == "__main__":
    main()
