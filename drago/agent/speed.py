"""The speed settings a run resolves on its own machine: ``agent.tdmpc.precision=auto`` and
``agent.tdmpc.compile=auto``.

``auto`` is each setting's default. A run resolves it once, when it starts, on the machine it starts on, and
writes the choice into its ``config.yaml``: a resumed run (on this machine or another) keeps what it began
with, so its numbers do not change halfway. Each setting can be forced (docs: Speed and precision).

* precision: bfloat16 autocast where the device multiplies bfloat16 matrices fast (a CUDA GPU with bfloat16
  support; a CPU with AVX-512 BF16 or AMX) *and* the networks are at least :data:`BFLOAT16_MIN_WIDTH` wide:
  narrower matmuls are too small to gain, and at width 128 on a CPU it slowed planning (docs: Benchmarks,
  the speed settings); float32 everywhere else.
* compile: ``torch.compile`` where it can work: a Python that TorchDynamo supports, plus a C++ compiler for
  the CPU backend or Triton on a GPU; eager elsewhere, with the reason.

PETS always runs in float32 and eager: ``auto`` resolves to those for it.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import sys
from pathlib import Path
from shutil import which

import torch

from drago.agent.protocol import capabilities_of
from drago.config import AgentConfig, Config, ConfigError

__all__ = ["BFLOAT16_MIN_WIDTH", "compile_cache_dir", "compile_problem", "fast_bfloat16", "resolve_agent_speed",
           "resolve_speed", "speed_summary", "use_compile_cache", "with_speed"]

#: The narrowest hidden width at which bfloat16 was measured to pay (docs: Benchmarks, the speed settings).
BFLOAT16_MIN_WIDTH = 512

_CPU_BFLOAT16_FLAGS = ("avx512_bf16", "amx_bf16")


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:  # not Linux: no flags to read, so no claim of fast bfloat16
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.partition(":")[2].split())
    return set()


def fast_bfloat16(device: torch.device) -> tuple[bool, str]:
    """(whether ``device`` multiplies bfloat16 matrices in hardware, why)."""
    if device.type == "cuda":
        if torch.cuda.is_bf16_supported(including_emulation=False):
            return True, f"{torch.cuda.get_device_name(device)} computes bfloat16"
        return False, f"{torch.cuda.get_device_name(device)} has no native bfloat16"
    found = [flag for flag in _CPU_BFLOAT16_FLAGS if flag in _cpu_flags()]
    if found:
        return True, f"this CPU has {' and '.join(found)}"
    return False, "this CPU has neither AVX-512 BF16 nor AMX"


def compile_problem(device: torch.device) -> str | None:
    """Why ``torch.compile`` cannot work here, or None when it can."""
    import torch._dynamo

    if not torch._dynamo.is_dynamo_supported():
        return f"torch {torch.__version__} cannot compile on Python {sys.version.split()[0]}"
    if device.type == "cuda":
        if importlib.util.find_spec("triton") is None:
            return "Triton, which compiles GPU kernels, is not installed"
        if torch.cuda.get_device_capability(device) < (7, 0):
            return "Triton needs a GPU of compute capability 7.0 or newer"
        return None
    compilers = [os.environ["CXX"]] if os.environ.get("CXX") else ["g++", "c++", "clang++"]
    if not any(which(c) for c in compilers):
        return f"no C++ compiler ({', '.join(compilers)}) for CPU kernels: install one (e.g. apt-get install g++)"
    return None


def resolve_agent_speed(agent: AgentConfig, device: torch.device) -> tuple[AgentConfig, list[str]]:
    """``agent`` with ``precision`` and ``compile`` resolved for ``device``, and one line for each ``auto`` that
    chose the slower path, saying why. Forced values are checked: a forced compile that cannot work is a
    :class:`~drago.config.ConfigError`."""
    notes: list[str] = []
    precision, compile_ = agent.tdmpc.precision, agent.tdmpc.compile
    if not capabilities_of(agent.kind).reduced_precision:
        return with_speed(agent, precision="float32" if precision == "auto" else precision,
                          compile="false" if compile_ == "auto" else compile_), notes
    if precision == "auto":
        fast, why = fast_bfloat16(device)
        wide = agent.tdmpc.mlp_dim >= BFLOAT16_MIN_WIDTH
        precision = "bfloat16" if fast and wide else "float32"
        if fast and not wide:
            notes.append(f"agent.tdmpc.precision=auto chose float32: {why}, but width {agent.tdmpc.mlp_dim} is under "
                         f"{BFLOAT16_MIN_WIDTH}, where bfloat16 does not pay")
    if compile_ != "false":
        problem = compile_problem(device)
        if problem is not None and compile_ == "true":
            raise ConfigError(f"agent.tdmpc.compile=true cannot work here: {problem}; or set agent.tdmpc.compile=false")
        if problem is not None:
            notes.append(f"agent.tdmpc.compile=auto runs eager: {problem}")
        compile_ = "false" if problem is not None else "true"
    return with_speed(agent, precision=precision, compile=compile_), notes


def with_speed(agent: AgentConfig, **speed: str) -> AgentConfig:
    """A copy of ``agent`` with the given TD-MPC speed settings (``precision``, ``compile``) replaced."""
    return dataclasses.replace(agent, tdmpc=dataclasses.replace(agent.tdmpc, **speed))


def resolve_speed(cfg: Config, device: torch.device) -> tuple[Config, list[str]]:
    """``cfg`` with its agent's speed settings resolved for ``device`` (see :func:`resolve_agent_speed`)."""
    agent, notes = resolve_agent_speed(cfg.agent, device)
    return dataclasses.replace(cfg, agent=agent), notes


def speed_summary(agent: AgentConfig) -> str:
    """The resolved speed settings in the words a run's first line uses, e.g. ``float32, compiled, fast tanh``."""
    if not capabilities_of(agent.kind).reduced_precision:
        return "float32, eager"
    parts = [agent.tdmpc.precision, "compiled" if agent.tdmpc.compile == "true" else "eager"]
    if agent.tdmpc.fast_tanh:
        parts.append("fast tanh")
    return ", ".join(parts)


def compile_cache_dir() -> Path:
    """Where compiled kernels are kept between runs: ``$TORCHINDUCTOR_CACHE_DIR`` when set, else
    ``$XDG_CACHE_HOME/drago/torchinductor`` (``~/.cache/drago/torchinductor``)."""
    if os.environ.get("TORCHINDUCTOR_CACHE_DIR"):
        return Path(os.environ["TORCHINDUCTOR_CACHE_DIR"])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "drago" / "torchinductor"


def use_compile_cache() -> Path:
    """Point inductor at :func:`compile_cache_dir` (before anything compiles) and return it. torch's own default
    is a folder in /tmp, emptied by a reboot, so every run after one would compile again."""
    path = compile_cache_dir()
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(path)
    return path
