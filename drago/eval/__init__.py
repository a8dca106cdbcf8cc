"""Evaluation of finished runs: world-model coverage (more measures and pictures come later)."""
