"""Restaurant task family (SPEC 3): table layouts, human behaviours and their motion.

A task = (table configuration, behaviour). A behaviour fixes, for each of the 6 people, a route
(landmark -> table seat, table seat -> landmark, or landmark -> landmark), a start delay and a
walking speed. Paths come from a pure-JAX crowd model integrated once per task with `lax.scan`:
goal attraction at the walking speed, repulsion (with a tangential slide) from tables and other
people, a speed limit, and a final projection that keeps people out of tables, apart from each
other and inside the walls. People stand still before their delay (nobody pushes a waiting person;
the walker goes around) and after reaching their goal.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from mpcpearl_jax.envs.types import NavConfig, TaskParams, stack_params

GRID_SPACING = 2.5
# 3x3 grid, row-major from the top-left (SPEC 3).
GRID = np.array(
    [[(c - 1) * GRID_SPACING, (1 - r) * GRID_SPACING] for r in range(3) for c in range(3)],
    dtype=np.float32,
)
# The authors' five configurations plus three more that open the start-goal corridor differently.
TABLE_CONFIGS: tuple[tuple[int, ...], ...] = (
    (0, 2, 4, 5, 7),
    (0, 4, 5, 6, 8),
    (1, 3, 4, 5, 8),
    (1, 2, 3, 4, 7),
    (2, 3, 4, 6, 7),
    (1, 3, 5, 7, 8),
    (0, 2, 3, 6, 8),
    (1, 2, 4, 6, 7),
)
LANDMARKS = {
    "kitchen": (-4.5, 3.0),
    "door1": (4.5, 0.5),
    "door2": (-2.0, 4.5),
    "toilet": (4.0, 3.5),
}
LANDMARK_NAMES = tuple(LANDMARKS)
LANDMARK_XY = np.array([LANDMARKS[k] for k in LANDMARK_NAMES], dtype=np.float32)
# Route templates of the authors' code: (from, to) with "table" meaning a seat at a table.
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
    ("kitchen", "door1"),
)
NUM_HUMANS = 6
NUM_TABLES = 5
TABLE_RADIUS = 0.5
NUM_TRAIN_BEHAVIOURS = 15
NUM_TEST_BEHAVIOURS = 3


@dataclasses.dataclass(frozen=True)
class CrowdModel:
    """Parameters of the crowd model (forces in m/s^2-like units per step)."""

    speed_range: tuple[float, float] = (2.8, 3.6)  # m/s while walking (authors' ~3.3)
    max_delay: int = 15  # steps
    seat_gap: float = 0.15  # clearance between a seated person and the table edge
    landmark_jitter: float = 0.5
    table_influence: float = 0.6  # repulsion acts within this clearance to a table
    human_influence: float = 0.5
    tangential: float = 1.0  # weight of the sideways slide around obstacles
    projection_iters: int = 48
    separation_margin: float = 1e-2  # people are kept this much further apart than 2 r_d


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
    (still waiting for their start) stays put and the other one of an overlapping pair moves.
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
        # out of tables (exact)
        d = p[:, None, :] - tables[None, :, :]
        dn = jnp.linalg.norm(d, axis=-1)
        push = jnp.maximum(min_table - dn, 0.0)
        p = p + jnp.sum(push[..., None] * _unit(d), axis=1)
        # inside the walls (tables stand well away from them)
        p = jnp.clip(p, bounds[0], bounds[1])
        return p, None

    p, _ = jax.lax.scan(one, p, None, length=iters)
    return p


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
    """
    dt = cfg.dt
    min_table = TABLE_RADIUS + cfg.human_radius + 1e-3  # the table push is exact
    # the pairwise push is iterative and the table push may undo a little of it: aim wider
    min_human = 2 * cfg.human_radius + model.separation_margin
    bounds = (
        jnp.asarray(cfg.arena_lo) + cfg.human_radius,
        jnp.asarray(cfg.arena_hi) - cfg.human_radius,
    )

    def step(p, t):
        to_goal = goal - p
        dist_goal = jnp.linalg.norm(to_goal, axis=-1, keepdims=True)
        v_des = _unit(to_goal) * jnp.minimum(speed[:, None], dist_goal / dt)
        # repulsion from tables, with a slide along the tangent on the goal side
        d = p[:, None, :] - tables[None, :, :]
        clear = jnp.linalg.norm(d, axis=-1) - TABLE_RADIUS - cfg.human_radius
        w = jnp.clip(1.0 - clear / model.table_influence, 0.0, 1.0)[..., None]
        n = _unit(d)
        tang = _rot90(n)
        side = jnp.sign(jnp.sum(tang * to_goal[:, None, :], axis=-1, keepdims=True) + 1e-3)
        rep_t = jnp.sum(w * (n + model.tangential * side * tang), axis=1)
        # repulsion from other people
        dh = p[:, None, :] - p[None, :, :]
        clear_h = jnp.linalg.norm(dh, axis=-1) - 2 * cfg.human_radius + jnp.eye(p.shape[0]) * 1e3
        wh = jnp.clip(1.0 - clear_h / model.human_influence, 0.0, 1.0)[..., None]
        rep_h = jnp.sum(wh * (_unit(dh) + 0.5 * _rot90(_unit(dh))), axis=1)
        v = v_des + speed[:, None] * (rep_t + rep_h)
        v_norm = jnp.linalg.norm(v, axis=-1, keepdims=True)
        v = v * jnp.minimum(1.0, speed[:, None] / (v_norm + 1e-6))
        moving = (t >= delay) & (dist_goal[:, 0] > 1e-3)
        p_new = jnp.where(moving[:, None], p + dt * v, p)
        p_new = _project(
            p_new, tables, min_table, min_human, model.projection_iters, bounds, t >= delay
        )
        # people who have started but stand (at their goal) may be pushed aside
        return p_new, p_new

    # start from a converged arrangement, so that waiting people are not nudged later
    p0 = _project(start, tables, min_table, min_human, 8 * model.projection_iters, bounds)
    _, path = jax.lax.scan(step, p0, jnp.arange(cfg.horizon))
    return jnp.concatenate([p0[None], path], axis=0)


@dataclasses.dataclass(frozen=True)
class Behaviour:
    """Routes, table slots, delays, speeds and jitter seeds of the 6 people (NumPy, host side)."""

    route: np.ndarray  # [H] index into ROUTES
    table_slot: np.ndarray  # [H] which of the 5 tables
    delay: np.ndarray  # [H] steps
    speed: np.ndarray  # [H] m/s
    seed: int


def sample_behaviour(rng: np.random.Generator, model: CrowdModel) -> Behaviour:
    # The first six routes are the authors' set; the behaviour permutes and varies them.
    route = rng.choice(len(ROUTES), size=NUM_HUMANS, replace=False)
    return Behaviour(
        route=route.astype(np.int32),
        table_slot=rng.integers(0, NUM_TABLES, size=NUM_HUMANS).astype(np.int32),
        delay=rng.integers(0, model.max_delay + 1, size=NUM_HUMANS).astype(np.int32),
        speed=rng.uniform(*model.speed_range, size=NUM_HUMANS).astype(np.float32),
        seed=int(rng.integers(0, 2**31 - 1)),
    )


def behaviour_endpoints(
    beh: Behaviour, tables: np.ndarray, model: CrowdModel, cfg: NavConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Start and goal points [H, 2] of a behaviour on a given table layout."""
    rng = np.random.default_rng(beh.seed)
    starts, goals = [], []
    for h in range(NUM_HUMANS):
        src, dst = ROUTES[beh.route[h]]
        pts = []
        for name in (src, dst):
            if name == "table":
                angle = rng.uniform(-np.pi, np.pi)
                r = TABLE_RADIUS + cfg.human_radius + model.seat_gap
                pts.append(tables[beh.table_slot[h]] + r * np.array([np.cos(angle), np.sin(angle)]))
            else:
                pts.append(
                    np.asarray(LANDMARKS[name]) + rng.uniform(-1, 1, 2) * model.landmark_jitter
                )
        starts.append(pts[0])
        goals.append(pts[1])
    lo = np.asarray(cfg.arena_lo) + cfg.human_radius
    hi = np.asarray(cfg.arena_hi) - cfg.human_radius
    return (
        np.clip(np.array(starts), lo, hi).astype(np.float32),
        np.clip(np.array(goals), lo, hi).astype(np.float32),
    )


def table_layout(config_index: int, shift: float = 0.0) -> np.ndarray:
    """Table centres [5, 2] of a configuration, optionally shifted left by `shift` metres."""
    centres = GRID[list(TABLE_CONFIGS[config_index])].copy()
    centres[:, 0] -= shift
    return centres


def build_task(
    tables: np.ndarray, beh: Behaviour, cfg: NavConfig, model: CrowdModel = CrowdModel()
) -> TaskParams:
    start, goal = behaviour_endpoints(beh, tables, model, cfg)
    path = _simulate_jit(
        jnp.asarray(start),
        jnp.asarray(goal),
        jnp.asarray(beh.delay),
        jnp.asarray(beh.speed),
        jnp.asarray(tables),
        cfg,
        model,
    )
    n_s = tables.shape[0]
    return TaskParams(
        human_pos=path.astype(jnp.float32),
        human_mask=jnp.ones(path.shape[:2], dtype=bool),
        static_lo=jnp.asarray(tables),
        static_hi=jnp.asarray(tables),
        static_radius=jnp.full((n_s,), TABLE_RADIUS, jnp.float32),
        start=jnp.array([-4.5, 4.5, -jnp.pi / 8], jnp.float32),
        goal=jnp.array([3.5, -3.5], jnp.float32),
    )


_simulate_jit = jax.jit(simulate_crowd, static_argnums=(5, 6))


def behaviours(seed: int, model: CrowdModel = CrowdModel()) -> list[Behaviour]:
    """The 15 training and 3 held-out behaviours for a seed (train first)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 20231]))
    return [sample_behaviour(rng, model) for _ in range(NUM_TRAIN_BEHAVIOURS + NUM_TEST_BEHAVIOURS)]


def make_restaurant_tasks(split: str, seed: int, cfg: NavConfig) -> TaskParams:
    """Stacked tasks of a split: train 8x15 = 120, test 8x3 = 24, ood 8x3 = 24 (shifted tables)."""
    behs = behaviours(seed)
    if split == "train":
        pairs = [
            (c, b, 0.0) for c in range(len(TABLE_CONFIGS)) for b in range(NUM_TRAIN_BEHAVIOURS)
        ]
    else:
        held_out = range(NUM_TRAIN_BEHAVIOURS, NUM_TRAIN_BEHAVIOURS + NUM_TEST_BEHAVIOURS)
        rng = np.random.default_rng(np.random.SeedSequence([seed, 777]))
        pairs = []
        for c in range(len(TABLE_CONFIGS)):
            shift = float(rng.uniform(0.5, 1.0)) if split == "ood" else 0.0
            pairs += [(c, b, shift) for b in held_out]
    tasks = [build_task(table_layout(c, s), behs[b], cfg) for c, b, s in pairs]
    return stack_params(tasks)
