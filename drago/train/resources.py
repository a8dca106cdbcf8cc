"""What a stretch of work costs the process: CPU seconds and peak resident memory.

CPU seconds rather than wall time make costs comparable between runs that shared the cores with
other jobs; the peak is reset at the start of the stretch where Linux allows it, so each task of a
run reports its own peak rather than the process's lifetime maximum.
"""

from __future__ import annotations

import gc
import resource
import sys
from pathlib import Path

import torch


class PeakMemory:
    """Peak resident set size of this process from ``start()`` on (Linux resets it through clear_refs)."""

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.resettable = False

    def start(self) -> None:
        gc.collect()
        try:
            Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
            self.resettable = True
        except OSError:
            self.resettable = False
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)

    def read(self) -> dict[str, float]:
        out: dict[str, float] = {}
        hwm = None
        status = Path("/proc/self/status")
        if self.resettable and status.exists():
            for line in status.read_text().splitlines():
                if line.startswith("VmHWM:"):
                    hwm = int(line.split()[1]) / 1024
        if hwm is None:
            # ru_maxrss is the peak of the whole process so far: KiB on Linux, bytes on macOS.
            hwm = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / (2**20 if sys.platform == "darwin" else 1024)
            out["peak_rss_is_process_lifetime"] = 1.0
        out["peak_rss_mib"] = hwm
        if self.device.type == "cuda":
            out["cuda_max_allocated_mib"] = torch.cuda.max_memory_allocated(self.device) / 2**20
        return out

