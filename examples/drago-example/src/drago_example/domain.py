"""Two pendulums: gymnasium's Pendulum-v1 with two rewards on the same dynamics."""

from __future__ import annotations

from drago.envs import Domain, gym_domain, reward_variant


def spin(obs, action, next_obs) -> float:
    """The angular speed as a fraction of its maximum (8 rad/s): the pendulum must keep turning."""
    return min(abs(float(next_obs[2])) / 8.0, 1.0)


def two_pendulums() -> Domain:
    return gym_domain("two-pendulums", {"swingup": "Pendulum-v1", "spin": reward_variant("Pendulum-v1", spin)},
                      episode_length=100, sequences={"two-pendulums": ("swingup", "spin")})
