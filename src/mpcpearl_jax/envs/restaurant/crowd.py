"""The restaurant's crowd (paper Sec. IV-A): people's behaviours, their plans, their motion.

As in the authors' scenarios, each of the 6 people walks one route (landmark -> seat at a table,
seat -> landmark, or landmark -> landmark) at a steady 2.8-3.6 m/s (the authors' people walk at
about 3.3 m/s for roughly the first 36 of the 80 steps), arrives within roughly the first 30-45
steps (start delay included) and then stands still exactly at the goal for the rest of the
episode. People ignore the robot but avoid each other and the tables.

A behaviour fixes, for each person, the route, a preferred landmark-table distance (on each layout
the seat is at the table whose distance from the route's landmark is nearest to it, so routes are
about 3.5-7 m long), a nominal start delay and speed, and a seed for the endpoints. On a given
table layout it becomes a plan (`plan_task`): endpoints apart from each other and from the tables
(seats 0.8 m from the table centre, just off its edge, on the side facing the landmark; landmark
points jittered; standing people far enough apart that a walker fits between them), and a speed
and a delay that let the route end by `CrowdModel.arrive_by`.

Paths come from a pure-JAX crowd model integrated once per task with `lax.scan` (`simulate_crowd`):
a walker heads for the goal at its speed, deflected by repulsion (with a sideways slide) from
tables, walls and other people; a walker within one step of its goal steps onto it and stays
there. A walker that stops getting closer to its goal goes round obstacles the other way. A
projection keeps walkers out of tables, apart from each other and inside the walls; people waiting
for their start or standing at their goal are never pushed (the walker goes around), and a step
that would still overlap is taken back. So people never overlap a table or each other, stand still
before their delay and after arriving, and end exactly at their goal unless blocked all episode.
The task catalogue that puts behaviours on table layouts is `generator`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from mpcpearl_jax.envs.types import NavConfig

LANDMARKS = {
    "kitchen": (-4.5, 3.0),
    "door1": (4.5, 0.5),
    "door2": (-2.0, 4.5),
    "toilet": (4.0, 3.5),
}
LANDMARK_NAMES = tuple(LANDMARKS)
LANDMARK_XY = np.array([LANDMARKS[k] for k in LANDMARK_NAMES], dtype=np.float32)
# Routes (from, to), "table" meaning a seat at a table. The first six are the authors' routes, the
# other four this project's; all can be walked within the first ~40 steps (no kitchen -> door1:
# 9 m is too far).
ROUTES = (
    ("door1", "table"),
    ("toilet", "table"),
    ("kitchen", "table"),
    ("table", "door1"),
    ("table", "kitchen"),
    ("door2", "toilet"),
    ("door2", "table"),
    ("table", "toilet"),
    ("table", "door2"),
    ("toilet", "door1"),
)
NUM_HUMANS = 6
TABLE_RADIUS = 0.5


@dataclasses.dataclass(frozen=True)
class CrowdModel:
    """Parameters of the crowd model (distances in m, times in steps; forces are unitless weights
    of the heading)."""

    speed_range: tuple[float, float] = (2.8, 3.6)  # m/s while walking (authors' ~3.3)
    max_delay: int = 12  # steps; the nominal start delay of a behaviour is at most this
    arrive_by: int = 42  # steps; delay and speed are chosen so that routes end about then
    detour: float = 1.15  # planned route length = detour * straight distance + detour_add
    detour_add: float = 0.3  # m
    reach_range: tuple[float, float] = (4.0, 6.5)  # m; preferred landmark-table distances
    seat_gap: float = 0.05  # clearance between a seated person and the table edge
    seat_spread: float = np.pi / 2  # seats lie within this angle of the side facing the landmark
    landmark_jitter: float = 0.5
    start_gap: float = 0.1  # clearance between a start and any other endpoint
    goal_gap: float = 0.55  # clearance between two goals: a walker fits between people standing
    table_influence: float = 0.6  # repulsion acts within this clearance to a table
    human_influence: float = 0.5
    wall_influence: float = 0.5
    contact: float = 0.05  # m; within this clearance a walker does not step towards a person
    tangential: float = 1.0  # weight of the sideways slide around obstacles
    goal_fade: float = 0.8  # m; repulsion fades out linearly within this distance of the goal
    projection_iters: int = 48
    separation_margin: float = 1e-2  # people are kept this much further apart than 2 r_d
    progress: float = 0.02  # m; getting this much closer to the goal counts as progress
    stall_steps: int = 6  # after this many steps without progress a walker goes round one way
    release: float = 0.3  # m; ... until it is this much closer to the goal
    revert_iters: int = 4  # rounds of taking back steps that still overlap
    max_push: float = 1.08  # a step, pushes included, is at most this many top-speed steps long


def _unit(v: Array, eps: float = 1e-6) -> Array:
    return v / (jnp.linalg.norm(v, axis=-1, keepdims=True) + eps)


def _rot90(v: Array) -> Array:
    return jnp.stack([-v[..., 1], v[..., 0]], axis=-1)


def _project(
    p: Array,
    tables: Array,
    min_table: float,
    min_human: float,
    iters: int,
    bounds: tuple[Array, Array],
    mobile: Array | None = None,
) -> Array:
    """Push people [H, 2] out of the table discs, apart from each other and inside `bounds`.

    `mobile` [H] bool marks who may be pushed (default: everyone); a person who is not mobile
    (waiting for their start, or standing at their goal) stays put and the other one of an
    overlapping pair moves.
    """
    m = jnp.ones(p.shape[0]) if mobile is None else mobile.astype(p.dtype)
    # share of an overlap taken by i in the pair (i, j): 1/2 if both mobile, 1 if j is not
    share = m[:, None] / jnp.maximum(m[:, None] + m[None, :], 1e-6)

    def one(p, _):
        # people apart (Jacobi)
        diff = p[:, None, :] - p[None, :, :]
        dist = jnp.linalg.norm(diff, axis=-1) + jnp.eye(p.shape[0]) * 1e3
        overlap = jnp.maximum(min_human - dist, 0.0)
        p = p + jnp.sum((share * overlap)[..., None] * _unit(diff), axis=1)
        # out of tables (exact; only people who may move ever overlap one)
        d = p[:, None, :] - tables[None, :, :]
        dn = jnp.linalg.norm(d, axis=-1)
        push = jnp.maximum(min_table - dn, 0.0) * m[:, None]
        p = p + jnp.sum(push[..., None] * _unit(d), axis=1)
        # inside the walls (tables stand well away from them)
        p = jnp.clip(p, bounds[0], bounds[1])
        return p, None

    p, _ = jax.lax.scan(one, p, None, length=iters)
    return p


def _overlapping(p: Array, tables: Array, min_table: float, min_human: float) -> Array:
    """[H] bool: who overlaps a table or another person (by more than float noise)."""
    dh = jnp.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1) + jnp.eye(p.shape[0]) * 1e3
    dt_ = jnp.linalg.norm(p[:, None, :] - tables[None, :, :], axis=-1)
    return jnp.any(dh < min_human, axis=1) | jnp.any(dt_ < min_table, axis=1)


def simulate_crowd(
    start: Array,
    goal: Array,
    delay: Array,
    speed: Array,
    tables: Array,
    cfg: NavConfig,
    model: CrowdModel = CrowdModel(),
) -> Array:
    """Integrate the crowd model. Returns positions [T + 1, H, 2].

    Args:
      start, goal: [H, 2]; delay: [H] int steps; speed: [H] m/s; tables: [S, 2] centres.

    Person h stands at `start[h]` up to step `delay[h]`, then walks at `speed[h]` (slower only
    while sliding along an obstacle) until it is within one step of `goal[h]`, steps onto the goal
    and stands there. Valid start positions (apart, clear of tables) give paths that never overlap.
    """
    dt = cfg.dt
    min_table = TABLE_RADIUS + cfg.human_radius + 1e-3  # the table push is exact
    # the pairwise push is iterative and the table push may undo a little of it: aim wider
    min_human = 2 * cfg.human_radius + model.separation_margin
    # a step is taken back if it still overlaps by more than this (float noise)
    ok_table = TABLE_RADIUS + cfg.human_radius + 1e-4
    ok_human = 2 * cfg.human_radius + 1e-4
    bounds = (
        jnp.asarray(cfg.arena_lo) + cfg.human_radius,
        jnp.asarray(cfg.arena_hi) - cfg.human_radius,
    )
    step_len = speed * dt
    max_move = model.max_push * model.speed_range[1] * dt

    def step(carry, t):
        p, arrived, best, stall, mode, patience, anchor = carry
        walking = (t >= delay) & ~arrived
        to_goal = goal - p
        dist_goal = jnp.linalg.norm(to_goal, axis=-1)
        # tables and walls matter less close to the goal (a seat is next to its table)
        fade = jnp.clip(dist_goal / model.goal_fade, 0.0, 1.0)[:, None, None]
        # repulsion from tables, with a slide along the tangent on the goal side (or, for a walker
        # that got stuck, always the same way round)
        d = p[:, None, :] - tables[None, :, :]
        clear = jnp.linalg.norm(d, axis=-1) - TABLE_RADIUS - cfg.human_radius
        w = fade * jnp.clip(1.0 - clear / model.table_influence, 0.0, 1.0)[..., None]
        n = _unit(d)
        tang = _rot90(n)
        side = jnp.sign(jnp.sum(tang * to_goal[:, None, :], axis=-1, keepdims=True) + 1e-3)
        fixed = mode[:, None, None]
        side = jnp.where(fixed == 0, side, fixed)
        rep_t = jnp.sum(w * (n + model.tangential * side * tang), axis=1)
        # repulsion from other people: pass a walker on one fixed side (both give way), slide
        # past a standing person like past a table
        dh = p[:, None, :] - p[None, :, :]
        clear_h = jnp.linalg.norm(dh, axis=-1) - 2 * cfg.human_radius + jnp.eye(p.shape[0]) * 1e3
        wh = jnp.clip(1.0 - clear_h / model.human_influence, 0.0, 1.0)[..., None]
        nh = _unit(dh)
        tang_h = _rot90(nh)
        side_h = jnp.sign(jnp.sum(tang_h * to_goal[:, None, :], axis=-1, keepdims=True) + 1e-3)
        side_h = jnp.where(fixed == 0, side_h, fixed)
        side_h = jnp.where(walking[None, :, None], 0.5 * jnp.where(fixed == 0, 1.0, fixed), side_h)
        rep_h = jnp.sum(wh * (nh + model.tangential * side_h * tang_h), axis=1)
        # repulsion from the walls (a standing person may block the strip along a wall)
        clear_lo = p - bounds[0]
        clear_hi = bounds[1] - p
        ww = fade[:, 0] * (
            jnp.clip(1.0 - clear_lo / model.wall_influence, 0.0, 1.0)
            - jnp.clip(1.0 - clear_hi / model.wall_influence, 0.0, 1.0)
        )
        # walk at the person's speed in the resulting direction; step onto a goal within reach
        heading = _unit(_unit(to_goal) + rep_t + rep_h + ww)
        # in contact with someone: slide past them rather than push them (pushes add to steps)
        contact = (clear_h < model.contact)[..., None]
        into = jnp.maximum(-jnp.sum(heading[:, None, :] * nh, axis=-1, keepdims=True), 0.0)
        heading = heading + jnp.sum(jnp.where(contact, into * nh, 0.0), axis=1)
        reach = dist_goal <= step_len
        p_walk = jnp.where(reach[:, None], goal, p + step_len[:, None] * heading)
        p_new = jnp.where(walking[:, None], p_walk, p)
        # walkers give way: only they are pushed (a walker that just reached its goal is not)
        p_new = _project(
            p_new, tables, min_table, min_human, model.projection_iters, bounds, walking & ~reach
        )

        # a push adds to a step: keep every step within max_push top-speed steps
        move = p_new - p
        move_len = jnp.linalg.norm(move, axis=-1, keepdims=True)
        p_new = p + move * jnp.minimum(1.0, max_move / jnp.maximum(move_len, 1e-9))

        # take back the steps of people who still overlap; if that does not settle it, all steps
        def bad(q):
            return _overlapping(q, tables, ok_table, ok_human)

        def take_back(q, _):
            return jnp.where(bad(q)[:, None], p, q), None

        p_new, _ = jax.lax.scan(take_back, p_new, None, length=model.revert_iters)
        p_new = jnp.where(jnp.any(bad(p_new)), p, p_new)
        arrived = arrived | jnp.all(p_new == goal, axis=-1)
        # a walker that gets no closer to its goal for `patience` steps goes round obstacles one
        # fixed way (then the other way, twice as patiently: it may be the long way round) until
        # it is `release` closer to the goal than where it got stuck
        d_new = jnp.linalg.norm(goal - p_new, axis=-1)
        progress = d_new < best - model.progress
        best = jnp.where(progress, d_new, best)
        stall = jnp.where(progress | ~walking, 0, stall + 1)
        stuck = stall >= patience
        mode = jnp.where(stuck, jnp.where(mode == 1.0, -1.0, 1.0), mode)
        stall = jnp.where(stuck, 0, stall)
        best = jnp.where(stuck, d_new, best)
        anchor = jnp.where(stuck, d_new, anchor)
        patience = jnp.where(stuck, 2 * patience, patience)
        released = (mode != 0) & (d_new < anchor - model.release)
        mode = jnp.where(released, 0.0, mode)
        patience = jnp.where(released, model.stall_steps, patience)
        return (p_new, arrived, best, stall, mode, patience, anchor), p_new

    # start from a valid arrangement (a no-op for the planned, well separated starts)
    p0 = _project(start, tables, min_table, min_human, 8 * model.projection_iters, bounds)
    h = start.shape[0]
    carry0 = (
        p0,
        jnp.zeros(h, dtype=bool),  # arrived
        jnp.linalg.norm(goal - p0, axis=-1),  # closest distance to the goal so far
        jnp.zeros(h, dtype=jnp.int32),  # steps without getting closer
        jnp.zeros(h, dtype=p0.dtype),  # 0: slide on the goal side; +-1: fixed way round
        jnp.full(h, model.stall_steps, dtype=jnp.int32),  # steps without progress tolerated
        jnp.zeros(h, dtype=p0.dtype),  # distance to the goal where the walker got stuck
    )
    _, path = jax.lax.scan(step, carry0, jnp.arange(cfg.horizon))
    return jnp.concatenate([p0[None], path], axis=0)


@dataclasses.dataclass(frozen=True)
class Behaviour:
    """Routes, seats, nominal delays and speeds, and the endpoint seed of the 6 people (NumPy).

    The actual delay and speed of a person on a table layout come from `plan_task`.
    """

    route: np.ndarray  # [H] index into ROUTES
    reach: np.ndarray  # [H] m; the seat is at the table whose distance from the route's landmark
    # is nearest to this
    delay: np.ndarray  # [H] nominal start delay, steps
    speed: np.ndarray  # [H] nominal speed, m/s
    seed: int


def sample_behaviour(rng: np.random.Generator, model: CrowdModel) -> Behaviour:
    # The first six routes are the authors' set; the behaviour permutes and varies them.
    route = rng.choice(len(ROUTES), size=NUM_HUMANS, replace=False)
    return Behaviour(
        route=route.astype(np.int32),
        reach=rng.uniform(*model.reach_range, size=NUM_HUMANS).astype(np.float32),
        delay=rng.integers(0, model.max_delay + 1, size=NUM_HUMANS).astype(np.int32),
        speed=rng.uniform(*model.speed_range, size=NUM_HUMANS).astype(np.float32),
        seed=int(rng.integers(0, 2**31 - 1)),
    )


@dataclasses.dataclass(frozen=True)
class Plan:
    """What the crowd model is given for one task (NumPy)."""

    start: np.ndarray  # [H, 2]
    goal: np.ndarray  # [H, 2]
    delay: np.ndarray  # [H] int32 steps
    speed: np.ndarray  # [H] float32 m/s


def plan_task(
    beh: Behaviour, tables: np.ndarray, cfg: NavConfig, model: CrowdModel = CrowdModel()
) -> Plan:
    """Endpoints, delays and speeds of a behaviour on a table layout [S, 2].

    Endpoints are drawn one after the other (starts and goals alike), each redrawn (further from
    its landmark, or at the next table) until it is clear of the tables and keeps `start_gap` of
    clearance to the ones drawn before, or `goal_gap` between two goals, so people never start or
    stand on top of each other and a walker fits between any two people standing at their goals.
    A seat lies `seat_gap` off the table edge, within `seat_spread` of the side facing the route's
    landmark, at the table whose distance from the landmark is nearest to the behaviour's `reach`.
    The speed is the nominal one, raised (up to the top of `speed_range`) when the planned route
    length could not be walked by `arrive_by` otherwise, and the delay is the nominal one, cut so
    that the route ends by `arrive_by`.
    """
    rng = np.random.default_rng(beh.seed)
    lo = np.asarray(cfg.arena_lo) + cfg.human_radius
    hi = np.asarray(cfg.arena_hi) - cfg.human_radius
    seat_r = TABLE_RADIUS + cfg.human_radius + model.seat_gap

    def gap(both_goals: bool) -> float:
        return model.goal_gap if both_goals else model.start_gap

    placed: list[tuple[np.ndarray, bool]] = []  # (point, is a goal)

    def draw(name: str, landmark: str, reach: float, is_goal: bool) -> np.ndarray:
        distance = np.linalg.norm(np.asarray(LANDMARKS[landmark]) - tables, axis=-1)
        by_preference = np.argsort(np.abs(distance - reach), kind="stable")
        for attempt in range(400):
            widen = 1.0 + (attempt % 100) / 25  # widen the search if the space is crowded
            if name == "table":  # a crowded table: try the next one
                table = by_preference[(attempt // 100) % len(tables)]
                towards = np.asarray(LANDMARKS[landmark]) - tables[table]
                facing = np.arctan2(towards[1], towards[0])
                angle = facing + rng.uniform(-1, 1) * model.seat_spread
                pt = tables[table] + seat_r * np.array([np.cos(angle), np.sin(angle)])
            else:
                jitter = rng.uniform(-1, 1, 2) * model.landmark_jitter * (widen + attempt // 100)
                pt = np.clip(np.asarray(LANDMARKS[name]) + jitter, lo, hi)
            clear_of_tables = np.min(np.linalg.norm(tables - pt, axis=-1)) >= seat_r - 1e-6
            if clear_of_tables and all(
                np.linalg.norm(pt - q) >= 2 * cfg.human_radius + gap(is_goal and q_goal)
                for q, q_goal in placed
            ):
                break
        else:  # pragma: no cover - the arena is far from full
            raise RuntimeError("no free endpoint found")
        placed.append((pt, is_goal))
        return pt

    starts, goals, delays, speeds = [], [], [], []
    for h in range(NUM_HUMANS):
        src, dst = ROUTES[beh.route[h]]
        landmark = dst if src == "table" else src
        starts.append(draw(src, landmark, float(beh.reach[h]), False))
        goals.append(draw(dst, landmark, float(beh.reach[h]), True))
        length = model.detour * np.linalg.norm(goals[-1] - starts[-1]) + model.detour_add
        speed = min(
            max(float(beh.speed[h]), length / (model.arrive_by * cfg.dt)), model.speed_range[1]
        )
        steps = int(np.ceil(length / (speed * cfg.dt)))
        delays.append(min(int(beh.delay[h]), max(0, model.arrive_by - steps)))
        speeds.append(speed)
    return Plan(
        start=np.array(starts, np.float32),
        goal=np.array(goals, np.float32),
        delay=np.array(delays, np.int32),
        speed=np.array(speeds, np.float32),
    )
