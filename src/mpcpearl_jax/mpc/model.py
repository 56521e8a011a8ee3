"""NumPy twin of the bicycle model (method §1) and its linearization, for the host-side SQP.

`bicycle_step` equals `mpcpearl_jax.envs.dynamics.bicycle_step` (tested); the plan itself is rolled
out
with `wrap=False` so that the heading is continuous along the horizon.
"""

from __future__ import annotations

import numpy as np


def slip_angle(delta: np.ndarray) -> np.ndarray:
    """beta = atan(tan(delta) / 2) written as atan2(sin(delta), 2 cos(delta)) (as dynamics.py)."""
    return np.arctan2(np.sin(delta), 2.0 * np.cos(delta))


def bicycle_step(
    pose: np.ndarray, u: np.ndarray, dt: float, wheelbase: float = 0.5, wrap: bool = True
) -> np.ndarray:
    """One Euler step. pose [..., 3], u [..., 2] physical (v, delta) -> [..., 3]."""
    theta, v = pose[..., 2], u[..., 0]
    beta = slip_angle(u[..., 1])
    x = pose[..., 0] + dt * v * np.cos(theta + beta)
    y = pose[..., 1] + dt * v * np.sin(theta + beta)
    th = theta + dt * v * 2.0 * np.sin(beta) / wheelbase  # cos(beta) tan(delta) / L
    if wrap:
        th = np.mod(th + np.pi, 2.0 * np.pi) - np.pi
    return np.stack([x, y, th], axis=-1)


def linearize(
    pose: np.ndarray, u: np.ndarray, dt: float, wheelbase: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of the unwrapped step: A [..., 3, 3] = df/dx, B [..., 3, 2] = df/du."""
    theta, v, delta = pose[..., 2], u[..., 0], u[..., 1]
    beta = slip_angle(delta)
    dbeta = 2.0 / (np.sin(delta) ** 2 + 4.0 * np.cos(delta) ** 2)
    c, s = np.cos(theta + beta), np.sin(theta + beta)
    shape = pose.shape[:-1]
    a = np.zeros(shape + (3, 3))
    a[..., 0, 0] = a[..., 1, 1] = a[..., 2, 2] = 1.0
    a[..., 0, 2] = -dt * v * s
    a[..., 1, 2] = dt * v * c
    b = np.zeros(shape + (3, 2))
    b[..., 0, 0] = dt * c
    b[..., 1, 0] = dt * s
    b[..., 0, 1] = -dt * v * s * dbeta
    b[..., 1, 1] = dt * v * c * dbeta
    b[..., 2, 0] = dt * 2.0 * np.sin(beta) / wheelbase
    b[..., 2, 1] = dt * v * 2.0 * np.cos(beta) * dbeta / wheelbase
    return a, b


def rollout(x0: np.ndarray, us: np.ndarray, dt: float, wheelbase: float = 0.5) -> np.ndarray:
    """Unwrapped rollout. x0 [3], us [K, 2] -> poses [K + 1, 3] (poses[0] = x0)."""
    xs = np.empty((us.shape[0] + 1, 3))
    xs[0] = x0
    for k in range(us.shape[0]):
        xs[k + 1] = bicycle_step(xs[k], us[k], dt, wheelbase, wrap=False)
    return xs


def box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from points p [..., 2] to boxes [lo, hi] ([..., 2]) and its gradient [..., 2].

    Inside a box the distance is 0 and the gradient points away from the box centre (a unit
    vector), so the tangent half-plane still pushes outwards.
    """
    proj = np.clip(p, lo, hi)
    diff = p - proj
    dist = np.linalg.norm(diff, axis=-1)
    away = p - 0.5 * (lo + hi)
    away_n = np.linalg.norm(away, axis=-1, keepdims=True)
    away = np.where(away_n > 1e-9, away / np.maximum(away_n, 1e-12), np.array([1.0, 0.0]))
    inside = dist[..., None] <= 1e-9
    grad = np.where(inside, away, diff / np.maximum(dist, 1e-12)[..., None])
    return dist, grad


def point_distance(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance |p - q| ([...]) and its gradient in p ([..., 2]); p, q broadcast to [..., 2]."""
    diff = p - q
    dist = np.linalg.norm(diff, axis=-1)
    grad = diff / np.maximum(dist, 1e-9)[..., None]
    return dist, grad


def saa_cvar(losses: np.ndarray, alpha: float) -> np.ndarray:
    """Exact SAA-CVaR min_xi xi + mean((L - xi)^+) / (1 - alpha) over the last axis [..., M].

    The minimiser is the empirical alpha-quantile, so the value is computed in closed form from the
    sorted losses (a fractional weight on the boundary sample).
    """
    m = losses.shape[-1]
    srt = np.sort(losses, axis=-1)[..., ::-1]  # descending
    tail = m * (1.0 - alpha)  # number of samples in the tail (may be fractional)
    n_full = int(np.floor(tail + 1e-9))
    frac = tail - n_full
    total = srt[..., :n_full].sum(axis=-1)
    if frac > 1e-9 and n_full < m:
        total = total + frac * srt[..., n_full]
    return total / tail
