"""drago: continual model-based reinforcement learning (DRAGO, ICML 2025) on a TD-MPC agent."""

__version__ = "0.1.0"
