"""Kinematic bicycle model of the car-like robot (method §1, paper Sec. IV).

This module is the single source of truth for the robot motion. Everything here is pure JAX,
jittable and vmappable; the host-side MPC keeps a NumPy twin that is tested equal.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

DELTA_MAX = jnp.pi / 2  # steering box [-pi/2, pi/2]


def wrap_angle(theta: Array) -> Array:
    """Wrap angles to [-pi, pi)."""
    return jnp.mod(theta + jnp.pi, 2.0 * jnp.pi) - jnp.pi


def slip_angle(delta: Array, wheelbase: float = 0.5) -> Array:
    """beta = atan(l_r tan(delta) / L) with l_r = L / 2, i.e. atan(tan(delta) / 2).

    Written as atan2(sin(delta), 2 cos(delta)), equal on |delta| < pi/2 and exact at the steering
    bounds, where float32 tan(+-pi/2) has the wrong sign and would flip the direction of motion.
    """
    del wheelbase  # l_r / L = 1/2 for any wheelbase
    return jnp.arctan2(jnp.sin(delta), 2.0 * jnp.cos(delta))


def bicycle_step(pose: Array, action: Array, dt: float, wheelbase: float = 0.5) -> Array:
    """One Euler step of the kinematic bicycle (paper Sec. IV, equations of motion).

    Args:
      pose: [..., 3] (x, y, theta).
      action: [..., 2] physical input (v, delta); not clipped here.
      dt: step length in seconds.
      wheelbase: L, distance between the axles.
    Returns:
      [..., 3] next pose with theta wrapped to [-pi, pi).
    """
    x, y, theta = pose[..., 0], pose[..., 1], pose[..., 2]
    v, delta = action[..., 0], action[..., 1]
    beta = slip_angle(delta, wheelbase)
    x_next = x + dt * v * jnp.cos(theta + beta)
    y_next = y + dt * v * jnp.sin(theta + beta)
    # cos(beta) tan(delta) / L == sin(beta) / l_r (l_r = L / 2), finite at delta = +-pi/2
    theta_next = theta + dt * v * 2.0 * jnp.sin(beta) / wheelbase
    return jnp.stack([x_next, y_next, wrap_angle(theta_next)], axis=-1)


def to_physical(action: Array, v_max: float) -> Array:
    """Map a normalized action in [-1, 1]^2 (clipped) affinely onto [0, v_max] x [-pi/2, pi/2]."""
    a = jnp.clip(action, -1.0, 1.0)
    v = (a[..., 0] + 1.0) * 0.5 * v_max
    delta = a[..., 1] * DELTA_MAX
    return jnp.stack([v, delta], axis=-1)


def to_normalized(u: Array, v_max: float) -> Array:
    """Inverse of :func:`to_physical` (inputs clipped to the box first)."""
    v = jnp.clip(u[..., 0], 0.0, v_max)
    delta = jnp.clip(u[..., 1], -DELTA_MAX, DELTA_MAX)
    return jnp.stack([2.0 * v / v_max - 1.0, delta / DELTA_MAX], axis=-1)
