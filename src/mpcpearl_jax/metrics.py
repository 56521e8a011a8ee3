"""Navigation metrics of the paper (method §8, authors' definitions), defined once.

Inputs are batches of evaluated episodes (any leading batch shape ``...``):
  position:  [..., T + 1, 2] robot positions including the start.
  collision: [..., T] bool, a real collision on that step.
  in_goal:   [..., T] bool, the position after that step is inside the goal radius.
  goal:      [..., 2].
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

METRIC_NAMES = ("SR", "TT", "CFR", "SPL", "MGD")


class EpisodeMetrics(NamedTuple):
    """Per-episode metrics, each shaped like the batch."""

    success: Array  # collision-free and reached the goal radius at some step
    collision_free: Array
    travel_time: Array  # T - steps inside the goal radius
    spl: Array  # success * l / max(P, l)
    mgd: Array  # mean squared distance to the goal over the steps


def episode_metrics(
    position: Array, collision: Array, in_goal: Array, goal: Array, robot_radius: float = 0.25
) -> EpisodeMetrics:
    """SR/CFR/TT/SPL/MGD ingredients for every episode of a batch."""
    horizon = collision.shape[-1]
    collision_free = ~jnp.any(collision, axis=-1)
    reached = jnp.any(in_goal, axis=-1)
    success = collision_free & reached
    travel_time = horizon - jnp.sum(in_goal, axis=-1)
    steps = jnp.linalg.norm(jnp.diff(position, axis=-2), axis=-1)
    path_len = jnp.sum(steps, axis=-1)
    shortest = jnp.linalg.norm(position[..., 0, :] - goal, axis=-1) - 2 * robot_radius
    spl = success * shortest / jnp.maximum(path_len, shortest)
    # mean over the T steps of the squared distance of the post-step position to the goal
    mgd = jnp.mean(jnp.sum((position[..., 1:, :] - goal[..., None, :]) ** 2, axis=-1), axis=-1)
    return EpisodeMetrics(success, collision_free, travel_time.astype(jnp.float32), spl, mgd)


def summarize(m: EpisodeMetrics) -> dict[str, float]:
    """Mean over all episodes (tasks): SR, TT, CFR, SPL, MGD as Python floats."""
    return {
        "SR": float(jnp.mean(m.success)),
        "TT": float(jnp.mean(m.travel_time)),
        "CFR": float(jnp.mean(m.collision_free)),
        "SPL": float(jnp.mean(m.spl)),
        "MGD": float(jnp.mean(m.mgd)),
    }


def compute(
    position: Array, collision: Array, in_goal: Array, goal: Array, robot_radius: float = 0.25
) -> dict[str, float]:
    """method §8 metrics averaged over a batch of episodes (one per test task)."""
    return summarize(episode_metrics(position, collision, in_goal, goal, robot_radius))
