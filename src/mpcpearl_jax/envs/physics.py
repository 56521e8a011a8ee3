"""Safety thresholds, the reward (paper eq. 2) and the MPC events (method §2, 5), defined once.

All functions act on a single environment (vmap for batches) and are pure JAX.
"""

from __future__ import annotations

from typing import Protocol

import jax.numpy as jnp
from jax import Array


class NavConfig(Protocol):
    """What these functions read of a family's constants; `envs.types.NavConfig` is one (this
    module sits below `envs` and imports nothing from it)."""

    @property
    def robot_radius(self) -> float: ...
    @property
    def human_radius(self) -> float: ...
    @property
    def r_safe(self) -> float: ...
    @property
    def eps_dynamic(self) -> float: ...
    @property
    def arena_lo(self) -> tuple[float, float]: ...
    @property
    def arena_hi(self) -> tuple[float, float]: ...
    @property
    def goal_radius(self) -> float: ...
    @property
    def q_weight(self) -> float: ...
    @property
    def r_weight(self) -> float: ...
    @property
    def cost_scale(self) -> float: ...
    @property
    def w_dynamic(self) -> float: ...
    @property
    def w_static(self) -> float: ...
    @property
    def w_goal(self) -> float: ...
    @property
    def goal_event_radius(self) -> float: ...
    @property
    def collision_event_factor(self) -> float: ...


class TaskParams(Protocol):
    """The static obstacles of a task as these functions read them (`envs.types.TaskParams`)."""

    @property
    def static_lo(self) -> Array: ...
    @property
    def static_hi(self) -> Array: ...
    @property
    def static_radius(self) -> Array: ...


def box_distance(p: Array, lo: Array, hi: Array) -> Array:
    """Euclidean distance from points p [..., 2] to axis-aligned boxes [lo, hi] (0 inside)."""
    d = jnp.maximum(jnp.maximum(lo - p, p - hi), 0.0)
    return jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-30) * (jnp.sum(d * d, axis=-1) > 0)


def static_clearance(p: Array, params: TaskParams) -> Array:
    """Distance [S] from the robot centre p [2] to the surface of every static obstacle."""
    return box_distance(p[None, :], params.static_lo, params.static_hi) - params.static_radius


def human_distance(p: Array, humans: Array) -> Array:
    """Centre distance [H] from p [2] to each human position humans [H, 2]."""
    return jnp.linalg.norm(humans - p[None, :], axis=-1)


def collides(p: Array, humans: Array, mask: Array, params: TaskParams, cfg: NavConfig) -> Array:
    """Real collision: |p - c| < r_r + r_obs for some present human or static obstacle."""
    hit_h = jnp.any(mask & (human_distance(p, humans) < cfg.robot_radius + cfg.human_radius))
    hit_s = jnp.any(static_clearance(p, params) < cfg.robot_radius)
    return hit_h | hit_s


def safety_violations(
    p: Array, humans: Array, mask: Array, params: TaskParams, cfg: NavConfig
) -> tuple[Array, Array]:
    """(n_d, n_s): numbers of humans / static obstacles whose safety threshold p violates.

    eps_d = r_r + r_d + r_safe (centre distance); eps_s = r_r + r_s + r_safe, i.e. a clearance to
    the obstacle surface below r_r + r_safe.
    """
    n_d = jnp.sum(mask & (human_distance(p, humans) < cfg.eps_dynamic))
    n_s = jnp.sum(static_clearance(p, params) < cfg.robot_radius + cfg.r_safe)
    return n_d, n_s


def reward(
    pos: Array, u: Array, n_d: Array, n_s: Array, next_pos: Array, goal: Array, cfg: NavConfig
) -> Array:
    """Paper eq. (2) as a reward, normalised as in the authors' code.

    r = -(|p_t - g|_Q^2 + u' R u) / 25 - w_d n_d - w_s n_s + w_g 1{|p_{t+1} - g| <= eps_g}
    with u the *physical* applied input (v, delta).
    """
    quad = cfg.q_weight * jnp.sum((pos - goal) ** 2) + cfg.r_weight * jnp.sum(u * u)
    bonus = cfg.w_goal * (jnp.linalg.norm(next_pos - goal) <= cfg.goal_radius)
    return -quad / cfg.cost_scale - cfg.w_dynamic * n_d - cfg.w_static * n_s + bonus


def events(p: Array, humans: Array, mask: Array, goal: Array, cfg: NavConfig) -> Array:
    """MPC trigger (method §5): goal event |p - g| <= 2 or a present human within 2 eps_d."""
    near_goal = jnp.linalg.norm(p - goal) <= cfg.goal_event_radius
    near_human = jnp.any(
        mask & (human_distance(p, humans) <= cfg.collision_event_factor * cfg.eps_dynamic)
    )
    return near_goal | near_human


def clip_to_arena(p: Array, cfg: NavConfig) -> Array:
    """Clip a position to the arena shrunk by the robot radius."""
    lo = jnp.asarray(cfg.arena_lo) + cfg.robot_radius
    hi = jnp.asarray(cfg.arena_hi) - cfg.robot_radius
    return jnp.clip(p, lo, hi)
