"""drago: continual model-based reinforcement learning (DRAGO, ICML 2025) on a TD-MPC agent.

The public API lives in :mod:`drago.api`; its names are reachable here (``drago.load_world_model``) and are
imported on first use, so ``import drago`` loads neither torch nor the trainer.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    # A submodule that is being imported is looked up here first: answer at once, without importing the API.
    if name.startswith("_") or name in ("api", "cli", "config", "envs", "agent", "continual", "training", "eval",
                                        "report", "seeding", "study"):
        raise AttributeError(f"module 'drago' has no attribute '{name}'")
    import drago.api

    if name in drago.api.__all__:
        return getattr(drago.api, name)
    raise AttributeError(f"module 'drago' has no attribute '{name}'")


def __dir__() -> list[str]:
    import drago.api

    return sorted([*globals(), *drago.api.__all__])
