"""The policy's observation from plain arrays, shared by `NavEnv.observe` and `deploy.observe`.

Everything a navigation policy sees is computed here, once: the env reads its arrays from
`TaskParams` and `EnvState`, a robot's control loop from its sensors
(`mpcpearl_jax.deploy.adapter`).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs.types import NavConfig


def obs_dim(config: NavConfig, num_people: int, num_static: int) -> int:
    """Length of the observation of a family with `num_people` people and `num_static` static
    obstacles under `config`'s observation options."""
    num_v = num_people if config.observe_velocity else 0
    num_s = num_static if config.observe_static else 0
    num_r = num_people + num_static + 1 if config.observe_relative else 0
    num_t = 1 if config.observe_time else 0
    num_f = 2 * num_people * config.observe_forecast
    num_p = num_people if config.observe_presence else 0
    return 3 + 2 * num_people + 2 * num_v + 2 * num_s + 2 * num_r + num_f + num_p + num_t


def normalize_xy(config: NavConfig, p: Array) -> Array:
    """Arena coordinates [..., 2] mapped to [-1, 1] (clipped)."""
    lo = jnp.asarray(config.arena_lo)
    hi = jnp.asarray(config.arena_hi)
    return jnp.clip(2.0 * (p - lo) / (hi - lo) - 1.0, -1.0, 1.0)


def observation(
    config: NavConfig,
    pose: Array,
    t: Array,
    humans: Array,
    mask: Array,
    prev: Array,
    prev_mask: Array,
    static_lo: Array,
    static_hi: Array,
    goal: Array,
) -> Array:
    """Observation [O] in [-1, 1] (`obs_dim`).

    Args:
      pose: [3] robot (x, y, heading); t: [] steps since the episode began.
      humans, mask: [H, 2] people positions and [H] presence at step t.
      prev, prev_mask: the same people at step t - 1 (at t = 0: those of step 0).
      static_lo, static_hi: [S, 2] static obstacles as boxes; goal: [2].

    Parts, in order: pose, people (absent ones at (-1, -1)), [people's last-step displacement
    (extension `observe_velocity`)], [static centres], [people, nearest static points and goal in
    the robot's frame (extension `observe_relative`)], [the elapsed time 2 t / T - 1 (extension
    `observe_time`)]. With the extension `sensing_radius` a person farther than it from the
    robot counts as absent throughout; with `observe_sorted` the people are listed nearest first
    in every part.
    """
    dist = jnp.linalg.norm(humans - pose[:2], axis=-1)
    if config.sensing_radius > 0:  # extension: people out of range look absent
        mask = mask & (dist <= config.sensing_radius)
    if config.observe_sorted:  # extension: nearest person first
        order = jnp.argsort(jnp.where(mask, dist, jnp.inf), stable=True)
        humans, mask, prev, prev_mask = (x[order] for x in (humans, mask, prev, prev_mask))
    h = jnp.where(mask[:, None], normalize_xy(config, humans), -1.0)
    parts = [normalize_xy(config, pose[:2]), pose[2:3] / jnp.pi, h.reshape(-1)]
    if config.observe_velocity:  # extension: people's last-step displacement
        scale = config.velocity_scale * config.dt
        vel = jnp.clip((humans - prev) / scale, -1.0, 1.0)
        parts.append(jnp.where((mask & prev_mask)[:, None], vel, 0.0).reshape(-1))
    if config.observe_static:
        parts.append(normalize_xy(config, 0.5 * (static_lo + static_hi)).reshape(-1))
    if config.observe_relative:  # extension: egocentric positions
        pos, th = pose[:2], pose[2]
        c, s = jnp.cos(th), jnp.sin(th)

        def ego(q: Array) -> Array:  # world points [N, 2] -> robot frame, scaled, clipped
            d = q - pos
            local = jnp.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
            return jnp.clip(local / config.relative_scale, -1.0, 1.0)

        nearest = jnp.clip(pos, static_lo, static_hi)  # [S, 2]
        parts.append(jnp.where(mask[:, None], ego(humans), 1.0).reshape(-1))
        parts.append(ego(nearest).reshape(-1))
        parts.append(ego(goal[None]).reshape(-1))
        if config.observe_forecast > 0:  # extension: constant-velocity foresight
            step = jnp.where((mask & prev_mask)[:, None], humans - prev, 0.0)  # [H, 2]
            k = config.forecast_stride * jnp.arange(1, config.observe_forecast + 1)
            ahead = humans[:, None, :] + k[None, :, None] * step[:, None, :]  # [H, K, 2]
            fut = jnp.stack([ego(ahead[:, i]) for i in range(config.observe_forecast)], 1)
            parts.append(jnp.where(mask[:, None, None], fut, 1.0).reshape(-1))
    if config.observe_presence:  # extension: who is there, for a crowd encoder's mask
        parts.append(jnp.where(mask, 1.0, -1.0))
    if config.observe_time:  # extension: elapsed fraction of the episode
        parts.append((2.0 * t / config.horizon - 1.0).reshape(1))
    return jnp.concatenate(parts).astype(jnp.float32)


def layout(config: NavConfig, num_people: int, num_static: int) -> list[dict]:
    """The parts of the observation as [{name, start, size, meaning}] (for documentation and the
    sidecar of an exported policy)."""
    h, s = num_people, num_static
    parts = [
        ("robot_xy", 2, "robot position, arena mapped to [-1, 1]"),
        ("robot_heading", 1, "heading / pi"),
        ("people_xy", 2 * h, "people positions, arena mapped to [-1, 1]; absent (-1, -1)"),
    ]
    if config.observe_velocity:
        what = f"people's last-step displacement / ({config.velocity_scale:g} m/s * dt), clipped"
        parts.append(("people_velocity", 2 * h, what + "; 0 if absent now or a step ago"))
    if config.observe_static:
        parts.append(("static_centres", 2 * s, "static obstacle centres, mapped to [-1, 1]"))
    if config.observe_relative:
        scale = f"/ {config.relative_scale:g} m, clipped to [-1, 1]"
        parts.append(("people_ego", 2 * h, f"people in the robot frame {scale}; absent (1, 1)"))
        parts.append(("static_ego", 2 * s, f"nearest static points in the robot frame {scale}"))
        parts.append(("goal_ego", 2, f"goal in the robot frame {scale}"))
        if config.observe_forecast > 0:
            k, st = config.observe_forecast, config.forecast_stride
            what = f"each person's position {st}, ..., {k * st} steps ahead at constant velocity"
            parts.append(
                ("people_forecast", 2 * h * k, f"{what}, [H, {k}, 2] in the robot frame {scale}")
            )
    if config.observe_presence:
        parts.append(("people_present", h, "1 if the person is present (and in range), else -1"))
    if config.observe_time:
        parts.append(("time", 1, "2 t / T - 1, T the episode length in steps"))
    out, start = [], 0
    for name, size, meaning in parts:
        out.append({"name": name, "start": start, "size": size, "meaning": meaning})
        start += size
    return out
