"""drago: continual model-based reinforcement learning (DRAGO, ICML 2025) on a TD-MPC agent."""

__version__ = "0.1.0"

from drago.api import load_world_model  # noqa: E402 (light: torch is imported on first load)
