"""Navigation metrics of the paper (method §8, authors' definitions), defined once.

`METRICS` is the one table of the metrics: name, the per-episode value it averages, which way is
better and how it is printed; the evaluator, the scoring, the reports and the table generator
read it (`metric_values`, `METRIC_NAMES`, `LOWER_IS_BETTER`, `format_metric`).

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

from mpcpearl_jax.envs import physics


class Metric(NamedTuple):
    """One metric of method §8 as it is reported: the mean over episodes of an `EpisodeMetrics`
    field."""

    name: str  # as reported: SR, TT, CFR, SPL, MGD
    field: str  # the `EpisodeMetrics` field it averages
    higher_is_better: bool
    decimals: int  # printed with this many decimals
    meaning: str

    def format(self, x: float) -> str:
        return f"{x:.{self.decimals}f}"


# method §8, in the paper's order
METRICS: dict[str, Metric] = {
    m.name: m
    for m in (
        Metric("SR", "success", True, 2, "success rate: collision-free and reached the goal"),
        Metric("TT", "travel_time", False, 2, "travel time: steps not spent at the goal"),
        Metric("CFR", "collision_free", True, 2, "collision-free rate"),
        Metric("SPL", "spl", True, 2, "success weighted by (shortest) path length"),
        Metric("MGD", "mgd", False, 2, "mean squared distance to the goal over the steps"),
    )
}
METRIC_NAMES = tuple(METRICS)
LOWER_IS_BETTER = frozenset(n for n, m in METRICS.items() if not m.higher_is_better)


def format_metric(name: str, x: float) -> str:
    """x as metric `name` is printed."""
    return METRICS[name].format(x)


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


def metric_values(m: EpisodeMetrics) -> dict[str, Array]:
    """Each metric of `METRICS` by name -> its per-episode values (the batch's shape)."""
    return {name: getattr(m, spec.field) for name, spec in METRICS.items()}


def summarize(m: EpisodeMetrics) -> dict[str, float]:
    """Mean over all episodes (tasks) of every metric (`METRICS`), as Python floats."""
    return {k: float(jnp.mean(v)) for k, v in metric_values(m).items()}


def compute(
    position: Array, collision: Array, in_goal: Array, goal: Array, robot_radius: float = 0.25
) -> dict[str, float]:
    """method §8 metrics averaged over a batch of episodes (one per test task)."""
    return summarize(episode_metrics(position, collision, in_goal, goal, robot_radius))


class FirstContact(NamedTuple):
    """Where an episode's first real collision happened, per episode (batch shape kept)."""

    step: Array  # int, the step of the first collision; -1 for a collision-free episode
    with_person: Array  # bool, the nearer obstacle at that step was a person (else static)
    steps_in_contact: Array  # int, steps with a collision in the whole episode
    reached_after: Array  # bool, the goal radius was reached after the first collision


def first_contact(
    position: Array,
    collision: Array,
    in_goal: Array,
    params,
    robot_radius: float,
    human_radius: float,
) -> FirstContact:
    """Failure analysis of one episode (vmap for a batch); not a metric of the paper.

    position [T + 1, 2], collision / in_goal [T], params: the episode's TaskParams (people and
    static geometry). A blocked move leaves no attempted position behind, so the obstacle hit on
    step t is the one with the smallest contact margin from the position before the step, p_t,
    against the obstacles at t + 1 (where the collision test reads them, method §2):
    |p_t - c| - (r_r + r_d) for a present person, the clearance to a table's surface minus r_r
    for a static obstacle.
    """
    horizon = collision.shape[-1]
    hit = jnp.any(collision)
    step = jnp.where(hit, jnp.argmax(collision), -1)
    t = jnp.maximum(step, 0)
    p = position[t]
    person = physics.human_distance(p, params.human_pos[t + 1]) - (robot_radius + human_radius)
    person = jnp.min(jnp.where(params.human_mask[t + 1], person, jnp.inf))
    static = jnp.min(physics.static_clearance(p, params), initial=jnp.inf) - robot_radius
    after = in_goal & (jnp.arange(horizon) > step)
    return FirstContact(
        step=step,
        with_person=hit & (person < static),
        steps_in_contact=jnp.sum(collision),
        reached_after=hit & jnp.any(after),
    )
