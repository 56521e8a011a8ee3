"""Types shared by every navigation task family.

`NavConfig` holds what is fixed for a whole family (a frozen dataclass, validated on construction,
static under jit). `TaskParams` holds everything that varies by task and is stacked on a leading
axis for many tasks; `EnvState` holds what changes within an episode (gymnax style).

Static obstacles of every family are *rounded boxes*: the set of points within `radius` of the
axis-aligned box [lo, hi]. A round table is a box with lo == hi and radius r_s; a building or a
parked car is a box with radius 0. One distance function therefore serves both environments.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from jax import Array

from mpcpearl_jax import validate


@dataclasses.dataclass(frozen=True)
class NavConfig:
    """Constants of a navigation task family (method §1, 2, 5).

    Attributes are in metres, seconds and radians. `arena_lo`/`arena_hi` bound the robot centre
    before shrinking by `robot_radius`.
    """

    name: str = "restaurant"
    dt: float = 0.05
    horizon: int = 80  # T, steps per episode
    v_max: float = 7.0
    wheelbase: float = 0.5
    robot_radius: float = 0.25  # r_r = L / 2
    human_radius: float = 0.25  # r_d
    r_safe: float = 0.25  # paper 0.25; authors' code 0.125
    arena_lo: tuple[float, float] = (-5.0, -5.0)
    arena_hi: tuple[float, float] = (5.0, 5.0)
    goal_radius: float = 0.5  # eps_g = 2 r_r
    q_weight: float = 1.0  # Q = q I on position
    r_weight: float = 0.2  # R = r I on (v, delta)
    cost_scale: float = 25.0  # quadratic cost divided by this (authors' normalisation)
    w_dynamic: float = 20.0
    w_static: float = 20.0
    w_goal: float = 10.0
    goal_event_radius: float = 2.0
    collision_event_factor: float = 2.0  # event when a human is within factor * eps_d
    observe_static: bool = True  # restaurant: table centres are part of the observation
    # extension (off in the paper): each person's last-step displacement, divided by
    # velocity_scale * dt and clipped to [-1, 1], follows the people's positions in the
    # observation (0 for a person absent at t or t - 1, and at t = 0)
    observe_velocity: bool = False
    velocity_scale: float = 4.0  # m/s mapped to 1
    # extension (off in the paper): egocentric features appended to the observation: each
    # person's position (absent: (1, 1)), the nearest point of each static obstacle and the goal,
    # relative to the robot and rotated into its heading frame, divided by relative_scale and
    # clipped to [-1, 1]
    observe_relative: bool = False
    relative_scale: float = 5.0  # m mapped to 1
    # extension (off in the paper): limited sensing range; a person farther than sensing_radius
    # metres from the robot is reported as absent in every part of the observation (0 = the
    # paper's unlimited range). The MPC and the reward still see everybody.
    sensing_radius: float = 0.0
    # extension (off in the paper): the elapsed fraction of the episode, 2 t / T - 1, is the last
    # entry of the observation. Without it a state's value depends on the remaining time (the goal
    # bonus is paid on every step left) while nothing in the observation shows it.
    observe_time: bool = False
    # extension (off in the paper): the people are listed nearest first (by distance to the
    # robot, people out of sensing range and absent ones last, ties in index order) in every part
    # of the observation, instead of in the fixed order of their identities, so that an input
    # slot means "the k-th nearest person" whoever it is (as in crowd-navigation policies such as
    # CADRL); the MPC, the reward and the events are unchanged
    observe_sorted: bool = False
    # extension (off in the paper): foresight. Each person's positions observe_forecast points
    # ahead, at every forecast_stride steps (t + forecast_stride, ..., t + observe_forecast *
    # forecast_stride), extrapolated at constant velocity from the last-step displacement, in
    # the robot's frame as the egocentric entries (needs observe_relative; absent: (1, 1))
    observe_forecast: int = 0
    forecast_stride: int = 1
    # extension (off in the paper): each person's presence, 1 present (and within
    # sensing_radius) and -1 absent, so that a crowd encoder (`pearl.crowd_encoder`) masks the
    # absent people out instead of reading placeholder coordinates
    observe_presence: bool = False

    def __post_init__(self) -> None:
        validate.positive(
            self,
            "dt",
            "v_max",
            "wheelbase",
            "robot_radius",
            "human_radius",
            "goal_radius",
            "cost_scale",
            "goal_event_radius",
            "collision_event_factor",
            "velocity_scale",
            "relative_scale",
        )
        validate.nonnegative(
            self,
            "r_safe",
            "q_weight",
            "r_weight",
            "w_dynamic",
            "w_static",
            "w_goal",
        )
        validate.nonnegative(self, "sensing_radius")
        validate.ints(self, "horizon")
        validate.ints(self, "observe_forecast", lo=0)
        validate.ints(self, "forecast_stride")
        validate.check(
            self.observe_forecast == 0 or self.observe_relative,
            self,
            "observe_forecast",
            "the forecast is egocentric: set env.observe_relative=true with it",
        )
        validate.flags(
            self,
            "observe_static",
            "observe_velocity",
            "observe_relative",
            "observe_time",
            "observe_sorted",
            "observe_presence",
        )
        for f in ("arena_lo", "arena_hi"):
            p = getattr(self, f)
            ok = isinstance(p, (tuple, list)) and len(p) == 2 and all(map(validate.is_number, p))
            validate.check(ok, self, f, f"must be a pair (x, y), got {p!r}")
        validate.check(
            all(
                lo + 2 * self.robot_radius < hi
                for lo, hi in zip(self.arena_lo, self.arena_hi, strict=True)
            ),
            self,
            "arena_hi",
            "must exceed arena_lo by more than the robot diameter",
        )

    def replace(self, **changes: Any) -> NavConfig:
        return dataclasses.replace(self, **changes)

    @property
    def eps_dynamic(self) -> float:
        """Safety threshold to a human: eps_d = r_r + r_d + r_safe."""
        return self.robot_radius + self.human_radius + self.r_safe


@struct.dataclass
class TaskParams:
    """Everything that varies by task. Add a leading axis to stack tasks.

    Shapes (single task): T = horizon, H = humans, S = static obstacles.
      human_pos:   [T + 1, H, 2] positions of the people at every step (precomputed).
      human_mask:  [T + 1, H] bool, True where a person is present (absent ones are no obstacle).
      static_lo:   [S, 2] lower corner of each static box.
      static_hi:   [S, 2] upper corner.
      static_radius: [S] rounding radius (table radius r_s, or 0 for a plain box).
      start:       [3] start pose (x, y, theta).
      goal:        [2] goal position.
    """

    human_pos: Array
    human_mask: Array
    static_lo: Array
    static_hi: Array
    static_radius: Array
    start: Array
    goal: Array

    @property
    def num_tasks(self) -> int:
        """Size of the leading task axis (only for stacked params)."""
        return int(self.start.shape[0]) if self.start.ndim == 2 else 1


@struct.dataclass
class EnvState:
    """Per-episode state: robot pose [3] and step counter t (int32)."""

    pose: Array
    t: Array


@struct.dataclass
class StepInfo:
    """What a step reports besides the reward (all scalars for a single env).

    collision: a real collision was attempted this step (the robot did not move).
    in_goal:   next position is inside the goal radius.
    n_dynamic, n_static: safety-threshold violations counted in the reward.
    event:     the MPC trigger (goal or collision event) evaluated at the *pre-step* state.
    position:  robot position after the step [2].
    """

    collision: Array
    in_goal: Array
    n_dynamic: Array
    n_static: Array
    event: Array
    position: Array


def stack_params(params: list[TaskParams]) -> TaskParams:
    """Stack single-task params on a new leading axis."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *params)
