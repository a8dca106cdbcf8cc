"""What a stretch of work costs the process: CPU seconds and peak resident memory.

CPU seconds rather than wall time make costs comparable between runs that shared the cores with
other jobs; the peak is reset at the start of the stretch where Linux allows it, so each task of a
run reports its own peak rather than the process's lifetime maximum.
"""

from __future__ import annotations

import ctypes
import gc
import os
import platform
import resource
import sys
from pathlib import Path

import torch

from drago.config import ConfigError


# mallopt parameters, from glibc's malloc.h.
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
KEEP_FREED_MEMORY_ENV = "DRAGO_KEEP_FREED_MEMORY"


def keep_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory for reuse instead of handing it back to the kernel.

    By default glibc gives each large allocation a fresh mmap and returns free memory at the top of the heap
    to the kernel. The networks allocate and free the same large activations on every call, so each one
    came as new pages that the kernel zero-fills on first touch. At width 512 that was 180,000 page faults
    per planned action and 100,000-180,000 per DRAGO gradient step: a third of the planner's CPU time when
    two jobs shared the cores, 8-14% of a DRAGO step on an idle machine (docs: Speed and precision).
    With no mmaps and no trimming, both counts drop to zero; the price is a peak resident memory about 13%
    higher, since freed memory stays with the process until it exits.

    Process-wide, so it is applied where a process starts its work (``drago`` runs, the benchmarks), never
    on import. Set ``DRAGO_KEEP_FREED_MEMORY=0`` (or ``false``, ``no``, ``off``) to keep glibc's defaults.

    Returns:
        Whether the allocator was changed: False on other C libraries (macOS, musl) or when opted out.

    Raises:
        ConfigError: the environment variable holds something other than a yes or a no.
    """
    libc = _glibc()
    if not keep_freed_memory_requested() or libc is None:
        return False
    # The largest trim threshold mallopt accepts (an int): freed memory is never returned to the kernel.
    return bool(libc.mallopt(_M_MMAP_MAX, 0)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))


def keep_freed_memory_requested() -> bool:
    """Whether ``DRAGO_KEEP_FREED_MEMORY`` asks for :func:`keep_freed_memory` (unset: yes).

    Raises:
        ConfigError: it holds something other than a yes or a no.
    """
    value = os.environ.get(KEEP_FREED_MEMORY_ENV, "1").strip().lower()
    if value not in ("1", "true", "yes", "on", "0", "false", "no", "off"):
        raise ConfigError(f"environment variable {KEEP_FREED_MEMORY_ENV}={os.environ[KEEP_FREED_MEMORY_ENV]!r} "
                          "is not a yes or a no (1/0, true/false, yes/no, on/off); set it to 0 to keep glibc's "
                          "allocator defaults, or unset it")
    return value in ("1", "true", "yes", "on")


def _release_freed_memory() -> None:
    """Hand the memory that malloc keeps (:func:`keep_freed_memory`) back to the kernel, so a peak measured
    from here on is this stretch's own, not what an earlier one left in the heap."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


def _glibc() -> ctypes.CDLL | None:
    if platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


class PeakMemory:
    """Peak resident set size of this process from ``start()`` on (Linux resets it through clear_refs)."""

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.resettable = False

    def start(self) -> None:
        gc.collect()
        _release_freed_memory()
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

