"""The public API: what ``import drago`` offers (``drago.load_config``, ``drago.load_world_model``, ...).

``import drago`` itself stays fast: the package reaches these names on first use (PEP 562), so torch and
the trainer are loaded only when something needs them.
"""

from __future__ import annotations

from drago.config import Config
from drago.config import load_config as _load_settings
from drago.continual import check_method
from drago.eval.predictor import WorldModelPredictor, load_world_model

__all__ = ["WorldModelPredictor", "load_config", "load_world_model"]


def load_config(preset: str, overrides: list[str] | None = None, method: str | None = None,
                seed: int | None = None) -> Config:
    """A validated run config: a preset plus ``key=value`` overrides, with a method that exists.

    Args:
        preset: a packaged preset's name (``drago list`` shows them).
        overrides: strings ``section.key=value``, or ``key=value`` for a key unique across sections.
        method: shortcut for ``method.name=...``.
        seed: shortcut for ``train.seed=...``.

    Raises:
        drago.config.ConfigError: one line naming the bad preset, key, value or method.
    """
    return check_method(_load_settings(preset, overrides, method=method, seed=seed))
