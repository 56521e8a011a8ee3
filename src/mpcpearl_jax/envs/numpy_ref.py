"""A plain NumPy twin of the navigation environment (method §1-2), one environment at a time.

This is an independent re-derivation of the robot model, reward and events written straight from
the specification, in the style of the authors' code: Python scalars and small NumPy arrays,
stepped in a Python loop. It exists to check the JAX environment (tests compare the two step by
step) and as the baseline of the throughput benchmark. It never calls the JAX implementation.

Conventions shared with the JAX environment (both follow docs/method.md):
  * the normalized action in [-1, 1]^2 is clipped, then mapped affinely onto
    v in [0, v_max], delta in [-pi/2, pi/2];
  * once |p - g| <= r_r the robot is parked: zero speed is applied (steering unchanged);
  * the new position is clipped to the arena shrunk by r_r;
  * people are read at step t + 1 for the safety counts and the collision test;
  * n_d and n_s are counted at the *attempted* position (after clipping, before the collision
    freeze), so that a blocked collision is penalised like one that would have happened;
  * on a real collision (|p' - c| < r_r + r_obs) the whole pose stays where it was;
  * the reward uses the applied physical input u = (v, delta) and pays the goal bonus when the
    position after the step (after the freeze) is within eps_g of the goal;
  * the MPC event is evaluated at the pre-step state;
  * no early termination: `done` is True after `horizon` steps.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mpcpearl_jax.envs.types import NavConfig, TaskParams


def task_to_numpy(params: TaskParams, index: int | None = None) -> dict[str, np.ndarray]:
    """One task as a dict of float64/bool NumPy arrays.

    Args:
      params: single-task `TaskParams`, or stacked ones with a leading task axis.
      index: which task to take from stacked params (None for single-task params).
    Returns:
      dict with keys human_pos [T + 1, H, 2], human_mask [T + 1, H], static_lo [S, 2],
      static_hi [S, 2], static_radius [S], start [3], goal [2].
    """
    out = {}
    for name in ("human_pos", "human_mask", "static_lo", "static_hi", "static_radius"):
        out[name] = np.asarray(getattr(params, name))
    out["start"] = np.asarray(params.start)
    out["goal"] = np.asarray(params.goal)
    if index is not None:
        if out["start"].ndim != 2:
            raise ValueError("index given but params are not stacked (start must be [N, 3])")
        out = {k: v[index] for k, v in out.items()}
    elif out["start"].ndim != 1:
        raise ValueError(f"params are stacked ({out['start'].shape[0]} tasks); pass an index")
    for k, v in out.items():
        out[k] = v.astype(bool) if k == "human_mask" else v.astype(np.float64)
    return out


def wrap_to_pi(theta: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (theta + math.pi) % (2.0 * math.pi) - math.pi


def normalized_to_physical(action: np.ndarray, v_max: float) -> tuple[float, float]:
    """Clip a normalized action [2] to [-1, 1] and map it to (v, delta)."""
    a0 = min(max(float(action[0]), -1.0), 1.0)
    a1 = min(max(float(action[1]), -1.0), 1.0)
    v = v_max * (a0 + 1.0) / 2.0
    delta = a1 * math.pi / 2.0
    return v, delta


def bicycle(
    x: float, y: float, theta: float, v: float, delta: float, dt: float, wheelbase: float
) -> tuple[float, float, float]:
    """Kinematic bicycle with l_r = L / 2 (method §1); theta wrapped to [-pi, pi).

    beta = atan(tan(delta) / 2) and the yaw rate v cos(beta) tan(delta) / L are evaluated in their
    equivalent forms atan2(sin(delta), 2 cos(delta)) and v sin(beta) / l_r, which stay exact at
    the steering bounds delta = +-pi/2 where tan(delta) is infinite.
    """
    l_r = wheelbase / 2.0
    beta = math.atan2(l_r * math.sin(delta), wheelbase * math.cos(delta))
    x_new = x + dt * v * math.cos(theta + beta)
    y_new = y + dt * v * math.sin(theta + beta)
    theta_new = theta + dt * v * math.sin(beta) / l_r
    return x_new, y_new, wrap_to_pi(theta_new)


def rounded_box_clearance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray, rad: np.ndarray):
    """Distance [S] from point p [2] to the surface of rounded boxes ([S, 2], [S, 2], [S])."""
    out = np.empty(lo.shape[0])
    for i in range(lo.shape[0]):
        dx = max(lo[i, 0] - p[0], 0.0, p[0] - hi[i, 0])
        dy = max(lo[i, 1] - p[1], 0.0, p[1] - hi[i, 1])
        out[i] = math.hypot(dx, dy) - rad[i]
    return out


class NumpyNavEnv:
    """One navigation environment in NumPy: `reset()` and `step(action)`.

    Args:
      config: the family's `NavConfig`.
      task: one task from `task_to_numpy` (or anything with the same keys).
    """

    def __init__(self, config: NavConfig, task: dict[str, np.ndarray]):
        self.cfg = config
        self.task = task
        self.pose = np.zeros(3)
        self.t = 0

    # ----------------------------------------------------------------- API
    def reset(self) -> np.ndarray:
        """Put the robot on the start pose; returns the observation."""
        self.pose = np.array(self.task["start"], dtype=np.float64)
        self.t = 0
        return self.observe()

    def set_state(self, pose: np.ndarray, t: int) -> None:
        """Place the robot anywhere (used to test arbitrary states)."""
        self.pose = np.array(pose, dtype=np.float64)
        self.t = int(t)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict[str, Any]]:
        """Apply a normalized action [2]. Returns (obs, reward, done, info)."""
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (2,):
            raise ValueError(f"action must have shape (2,), got {action.shape}")
        cfg, task = self.cfg, self.task
        goal = task["goal"]
        x, y, theta = (float(c) for c in self.pose)
        event = self.event()

        v, delta = normalized_to_physical(action, cfg.v_max)
        if math.hypot(x - goal[0], y - goal[1]) <= cfg.robot_radius:
            v = 0.0  # parked
        xn, yn, thn = bicycle(x, y, theta, v, delta, cfg.dt, cfg.wheelbase)
        xn = min(max(xn, cfg.arena_lo[0] + cfg.robot_radius), cfg.arena_hi[0] - cfg.robot_radius)
        yn = min(max(yn, cfg.arena_lo[1] + cfg.robot_radius), cfg.arena_hi[1] - cfg.robot_radius)

        humans, mask = self._humans(self.t + 1)
        n_d, n_s, collision = self._contacts(np.array([xn, yn]), humans, mask)
        if collision:
            xn, yn, thn = x, y, theta

        cost = cfg.q_weight * ((x - goal[0]) ** 2 + (y - goal[1]) ** 2)
        cost += cfg.r_weight * (v * v + delta * delta)
        in_goal = math.hypot(xn - goal[0], yn - goal[1]) <= cfg.goal_radius
        r = -cost / cfg.cost_scale - cfg.w_dynamic * n_d - cfg.w_static * n_s
        r += cfg.w_goal * float(in_goal)

        self.pose = np.array([xn, yn, thn])
        self.t += 1
        info = dict(
            collision=collision,
            in_goal=in_goal,
            n_dynamic=n_d,
            n_static=n_s,
            event=event,
            position=self.pose[:2].copy(),
        )
        return self.observe(), float(r), self.t >= cfg.horizon, info

    # ------------------------------------------------------------- helpers
    def _humans(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """People [H, 2] and presence [H] at step t (the last step is held after the horizon)."""
        i = min(max(t, 0), self.task["human_pos"].shape[0] - 1)
        return self.task["human_pos"][i], self.task["human_mask"][i]

    def _contacts(self, p: np.ndarray, humans: np.ndarray, mask: np.ndarray):
        """(n_d, n_s, collision) at position p [2] against people [H, 2] and static obstacles."""
        cfg = self.cfg
        eps_d = cfg.robot_radius + cfg.human_radius + cfg.r_safe
        n_d, collision = 0, False
        for h in range(humans.shape[0]):
            if not mask[h]:
                continue
            d = math.hypot(p[0] - humans[h, 0], p[1] - humans[h, 1])
            n_d += int(d < eps_d)
            collision |= d < cfg.robot_radius + cfg.human_radius
        clear = rounded_box_clearance(
            p, self.task["static_lo"], self.task["static_hi"], self.task["static_radius"]
        )
        n_s = int(np.sum(clear < cfg.robot_radius + cfg.r_safe))
        collision |= bool(np.any(clear < cfg.robot_radius))
        return n_d, n_s, bool(collision)

    def event(self) -> bool:
        """MPC trigger (method §5) at the current state: near the goal or near a present person."""
        cfg = self.cfg
        p = self.pose[:2]
        if math.hypot(p[0] - self.task["goal"][0], p[1] - self.task["goal"][1]) <= (
            cfg.goal_event_radius
        ):
            return True
        humans, mask = self._humans(self.t)
        radius = cfg.collision_event_factor * (cfg.robot_radius + cfg.human_radius + cfg.r_safe)
        for h in range(humans.shape[0]):
            if mask[h] and math.hypot(p[0] - humans[h, 0], p[1] - humans[h, 1]) <= radius:
                return True
        return False

    def _scale(self, p: np.ndarray) -> np.ndarray:
        """Map arena coordinates [..., 2] to [-1, 1]."""
        lo = np.asarray(self.cfg.arena_lo, dtype=np.float64)
        hi = np.asarray(self.cfg.arena_hi, dtype=np.float64)
        return np.clip(2.0 * (p - lo) / (hi - lo) - 1.0, -1.0, 1.0)

    def observe(self) -> np.ndarray:
        """Observation [3 + 2H (+ 2S)]: pose, people (absent ones at (-1, -1)), static centres."""
        humans, mask = self._humans(self.t)
        h = np.where(mask[:, None], self._scale(humans), -1.0)
        parts = [self._scale(self.pose[:2]), np.array([self.pose[2] / math.pi]), h.ravel()]
        if self.cfg.observe_static:
            centres = 0.5 * (self.task["static_lo"] + self.task["static_hi"])
            parts.append(self._scale(centres).ravel())
        return np.concatenate(parts)
