"""Test-time safety shield (extension, off in the paper): a one-call geometric filter on actions.

The learned policy's failures are contacts (`docs/research-log.md`: most failing episodes touch a
person or a table, and half of those still reach the goal afterwards). The shield replaces an
action whose next `lookahead` steps, holding it, would bring the robot within `margin` of a
collision with what the robot can see, by the nearest action (in the normalised action box) of a
fixed candidate set that would not; when none would, by the one with the largest clearance. It
never changes a safe action, so an unshielded success stays one.

What the shield may use is what the observation holds: the people the robot senses now (within
`NavConfig.sensing_radius` when set), their last-step displacement, and the static obstacles.
People are predicted at constant velocity; nothing of their future is read. The robot's model is
the environment's own (`dynamics.bicycle_step`, arena clipping, parking at the goal). The check is
a single vectorised function of arrays, so it runs inside a jitted, vmapped rollout as a cheap
call next to the policy (shielding in the sense of Alshiekh et al., "Safe reinforcement learning
via shielding", AAAI 2018, with a hand-written geometric model instead of a synthesised one).

It is an evaluation and deployment option (`experiments.evaluate --shield`,
`mpcpearl_jax.evaluation.evaluate.make_evaluator(..., shield=ShieldConfig())`); training never uses
it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs import physics
from mpcpearl_jax.envs.dynamics import bicycle_step, to_physical
from mpcpearl_jax.envs.types import EnvState, NavConfig, TaskParams
from mpcpearl_jax.validate import is_int, is_number


@dataclasses.dataclass(frozen=True)
class ShieldConfig:
    """margin: extra clearance in metres required beyond contact (r_r + r_obs) from people and
    static obstacles; lookahead: steps the candidate action is held for the check (people at
    constant velocity); speeds, steers: the grid of candidate actions in the normalised action box
    (speed -1 stands still, 1 is v_max; steering +-1 is +-pi/2), to which the policy's own
    steering at every grid speed is added."""

    margin: float = 0.05
    lookahead: int = 2
    speeds: tuple[float, ...] = (-1.0, -0.5, 0.0, 0.5, 1.0)
    steers: tuple[float, ...] = (-1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5, 0.75, 1.0)

    def __post_init__(self) -> None:
        if not (is_number(self.margin) and 0.0 <= self.margin <= 1.0):
            raise ValueError(f"shield.margin: expected a number in [0, 1] m, got {self.margin!r}")
        if not (is_int(self.lookahead) and 1 <= self.lookahead <= 20):
            raise ValueError(
                f"shield.lookahead: expected an integer in [1, 20], got {self.lookahead!r}"
            )
        for name in ("speeds", "steers"):
            vals = getattr(self, name)
            if not vals or any(not -1.0 <= float(v) <= 1.0 for v in vals):
                raise ValueError(f"shield.{name}: expected values in [-1, 1], got {vals!r}")

    def candidates(self, action: Array) -> Array:
        """[K, 2] candidate normalised actions: the policy's own first, then its steering at every
        grid speed, then the speed x steering grid."""
        sp = jnp.asarray(self.speeds, jnp.float32)
        st = jnp.asarray(self.steers, jnp.float32)
        own_steer = jnp.stack([sp, jnp.full_like(sp, action[1])], -1)
        grid = jnp.stack(jnp.meshgrid(sp, st, indexing="ij"), -1).reshape(-1, 2)
        return jnp.concatenate([action[None].astype(jnp.float32), own_steer, grid], 0)


def clearance(
    pose: Array,
    actions: Array,
    people: Array,
    people_prev: Array,
    seen: Array,
    params: TaskParams,
    goal: Array,
    cfg: NavConfig,
    lookahead: int,
) -> Array:
    """Smallest clearance [K] (metres beyond contact) over `lookahead` steps of each candidate
    action [K, 2] held from `pose`, against the `seen` people [H] moving at their last-step
    displacement (people - people_prev) and the static obstacles of `params`."""
    vel = jnp.where(seen[:, None], people - people_prev, 0.0)
    contact_h = cfg.robot_radius + cfg.human_radius

    def one(a: Array) -> Array:
        p = pose
        worst = jnp.inf
        for k in range(1, lookahead + 1):
            u = to_physical(a, cfg.v_max)
            parked = jnp.linalg.norm(p[:2] - goal) <= cfg.robot_radius
            u = u.at[0].set(jnp.where(parked, 0.0, u[0]))
            cand = bicycle_step(p, u, cfg.dt, cfg.wheelbase)
            cand = cand.at[:2].set(physics.clip_to_arena(cand[:2], cfg))
            pred = people + k * vel
            d_h = physics.human_distance(cand[:2], pred) - contact_h
            c_h = jnp.min(jnp.where(seen, d_h, jnp.inf), initial=jnp.inf)
            c_s = jnp.min(
                physics.static_clearance(cand[:2], params) - cfg.robot_radius, initial=jnp.inf
            )
            worst = jnp.minimum(worst, jnp.minimum(c_h, c_s))
            p = cand
        return worst

    return jax.vmap(one)(actions)


def filter_action(
    action: Array,
    pose: Array,
    people: Array,
    people_prev: Array,
    seen: Array,
    params: TaskParams,
    cfg: NavConfig,
    shield: ShieldConfig,
) -> tuple[Array, Array]:
    """(executed action [2], intervened bool) for one robot: the policy's `action` when its
    clearance is at least `shield.margin`, else the nearest candidate that has it, else the
    candidate with the largest clearance."""
    action = jnp.clip(action, -1.0, 1.0)
    cands = shield.candidates(action)
    clear = clearance(
        pose, cands, people, people_prev, seen, params, params.goal, cfg, shield.lookahead
    )
    safe = clear >= shield.margin
    dist = jnp.sum((cands - action) ** 2, axis=-1)
    best_safe = jnp.argmin(jnp.where(safe, dist, jnp.inf))
    best_any = jnp.argmax(clear)
    idx = jnp.where(safe[0], 0, jnp.where(jnp.any(safe), best_safe, best_any))
    return cands[idx], idx != 0


def shield_step(
    env, state: EnvState, action: Array, params: TaskParams, shield: ShieldConfig
) -> tuple[Array, Array]:
    """`filter_action` with what the robot observes in `env` at `state`: the people present at t
    (and within the sensing radius, if the environment limits it) and their positions at t - 1
    (no displacement at t = 0 or for a person absent at t - 1)."""
    cfg = env.config
    people, mask = env.humans_at(params, state.t)
    prev, prev_mask = env.humans_at(params, jnp.maximum(state.t - 1, 0))
    if cfg.sensing_radius > 0:
        dist = jnp.linalg.norm(people - state.pose[:2], axis=-1)
        mask = mask & (dist <= cfg.sensing_radius)
    prev = jnp.where((mask & prev_mask)[:, None], prev, people)
    return filter_action(action, state.pose, people, prev, mask, params, cfg, shield)
