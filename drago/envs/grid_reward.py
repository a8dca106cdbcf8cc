"""The grid's reward as a batched torch function of ``(obs, action, next_obs)``, exactly the env's.

Planning needs it on predicted transitions: the zero-shot evaluation (:mod:`drago.eval.zero_shot`) and a
PETS learner told the task's reward (``agent.pets.reward=known``; docs: Methods, PETS). It imports torch,
so :mod:`drago.envs` does not import it.
"""

from __future__ import annotations

import torch

from drago.envs.fourrooms import CENTRE, GOAL_RADIUS, SIZE
from drago.envs.tasks import GridTask

__all__ = ["decode_obs", "true_reward"]


def decode_obs(obs: torch.Tensor) -> torch.Tensor:
    """Torch :func:`~drago.eval.coverage.decode_batch`: (N, 3) observations -> (N, 3) int64 ``(x, y, dir)``.

    The same float64 arithmetic as :func:`~drago.envs.fourrooms.decode_observation` (round half to even,
    clipped to the map), so every row decodes as the grid decodes it; a non-finite row decodes to -1.
    """
    o = obs.detach().to(torch.float64).reshape(-1, 3)
    scaled = torch.stack([(o[:, 0] + 1.0) * SIZE / 2.0, (o[:, 1] + 1.0) * SIZE / 2.0, (o[:, 2] + 1.0) * 2.0], dim=1)
    upper = torch.tensor([SIZE - 1, SIZE - 1, 3], dtype=torch.float64, device=o.device)
    decoded = torch.minimum(torch.round(scaled).clamp_min(0.0), upper).to(torch.int64)
    finite = torch.isfinite(o).all(dim=1, keepdim=True)
    return torch.where(finite, decoded, torch.full_like(decoded, -1))


def true_reward(task: GridTask, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """The task's reward of a batch of transitions, exactly the env's (:func:`~drago.envs.fourrooms.grid_reward`).

    Positions are decoded from the observations with the grid's own decoding, so a predicted next
    observation is paid as the cell it decodes to. The action does not enter the reward: where the step
    leads does.

    Args:
        task: start, goal and reward type (``task.dense``).
        obs: (N, 3) observations before the step.
        action: (N, 3) one-hot actions (unused; kept for the (obs, action, next_obs) signature).
        next_obs: (N, 3) observations after the step.

    Returns:
        (N,) float64 rewards; 0 for a row whose observation or next observation is not finite.
    """
    del action
    prev = decode_obs(obs)
    now = decode_obs(next_obs)
    gx, gy = int(task.goal[0]), int(task.goal[1])
    px, py = now[:, 0], now[:, 1]
    valid = (prev >= 0).all(dim=1) & (now >= 0).all(dim=1)
    # The env's gate: strict in x, not in y, so row y = 13 counts and column x = 13 never does.
    gate = valid & ((px - CENTRE) * (gx - CENTRE) > 0) & ((py - CENTRE) * (gy - CENTRE) >= 0)
    on_goal = (px == gx) & (py == gy)
    if not task.dense:
        return (gate & on_goal).to(torch.float64)
    d2 = (px - gx) ** 2 + (py - gy) ** 2
    prev_d2 = (prev[:, 0] - gx) ** 2 + (prev[:, 1] - gy) ** 2
    shaping = (1.0 - torch.sqrt(d2.to(torch.float64)) / GOAL_RADIUS).clamp_min(0.0)
    reward = torch.where(on_goal | (d2 < prev_d2), shaping, torch.zeros_like(shaping)) + 2.0 * on_goal
    return torch.where(gate, reward, torch.zeros_like(reward))
