"""Restaurant task catalogue (paper Sec. IV-A): table layouts, behaviours per split, tasks.

A task = (table configuration, behaviour): 8 table layouts (the authors' five and three more) x
15 training behaviours, and 3 held-out behaviours per layout for test (OOD: the tables shifted
left) and 3 more for validation, each drawn from its own random stream of the task-set seed.
`build_task` puts a behaviour on a layout and integrates its crowd (`crowd.plan_task`,
`crowd.simulate_crowd`); `make_restaurant_tasks` stacks the tasks of a split, and
`redraw_train_tasks` draws fresh behaviours for training tasks (extension `redraw_behaviours`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mpcpearl_jax.envs.restaurant.crowd import (  # noqa: F401  (re-exported: the family's API)
    LANDMARK_NAMES,
    LANDMARK_XY,
    LANDMARKS,
    NUM_HUMANS,
    ROUTES,
    TABLE_RADIUS,
    Behaviour,
    CrowdModel,
    Plan,
    plan_task,
    sample_behaviour,
    simulate_crowd,
)
from mpcpearl_jax.envs.types import NavConfig, TaskParams, stack_params

GRID_SPACING = 2.5
# 3x3 grid of table positions, row-major from the top-left.
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
NUM_TABLES = 5
NUM_TRAIN_BEHAVIOURS = 15
NUM_TEST_BEHAVIOURS = 3


def table_layout(config_index: int, shift: float = 0.0) -> np.ndarray:
    """Table centres [5, 2] of a configuration, optionally shifted left by `shift` metres."""
    centres = GRID[list(TABLE_CONFIGS[config_index])].copy()
    centres[:, 0] -= shift
    return centres


def build_task(
    tables: np.ndarray, beh: Behaviour, cfg: NavConfig, model: CrowdModel = CrowdModel()
) -> TaskParams:
    plan = plan_task(beh, tables, cfg, model)
    path = _simulate_jit(
        jnp.asarray(plan.start),
        jnp.asarray(plan.goal),
        jnp.asarray(plan.delay),
        jnp.asarray(plan.speed),
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


def val_behaviours(seed: int, model: CrowdModel = CrowdModel()) -> list[Behaviour]:
    """The validation behaviours: held out from training like the test ones, but from their own
    stream, so settings can be chosen without looking at the test tasks."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 20231, 2]))
    return [sample_behaviour(rng, model) for _ in range(NUM_TEST_BEHAVIOURS)]


def split_behaviours(split: str, seed: int) -> list[Behaviour]:
    """Behaviours indexed as in `task_pairs`: 0..14 the paper's training set, 15..17 held out
    (test and OOD); the val split uses its own three."""
    return val_behaviours(seed) if split == "val" else behaviours(seed)


def _train_indices(train_behaviours: int) -> list[int]:
    """The first `train_behaviours` of the paper's 15 training behaviours: a smaller training
    split (8 x train_behaviours tasks) for tests and benchmarks. More than 15 per layout was an
    extension, removed (docs/extensions.md, Removed options)."""
    ok = isinstance(train_behaviours, int) and not isinstance(train_behaviours, bool)
    if not (ok and 1 <= train_behaviours <= NUM_TRAIN_BEHAVIOURS):
        raise ValueError(
            f"train_behaviours: must be an int in 1..{NUM_TRAIN_BEHAVIOURS} (a subset of the "
            f"paper's training behaviours), got {train_behaviours!r}"
        )
    return list(range(train_behaviours))


def task_pairs(
    split: str, seed: int, train_behaviours: int = NUM_TRAIN_BEHAVIOURS
) -> list[tuple[int, int, float]]:
    """(configuration, behaviour index, left shift) of each task of a split, in order.

    `train_behaviours` (training split only; the paper: 15) < 15 keeps the first ones only; the
    test and OOD tasks do not change."""
    if split == "train":
        idx = _train_indices(train_behaviours)
        return [(c, b, 0.0) for c in range(len(TABLE_CONFIGS)) for b in idx]
    if split == "val":
        return [(c, b, 0.0) for c in range(len(TABLE_CONFIGS)) for b in range(NUM_TEST_BEHAVIOURS)]
    held_out = range(NUM_TRAIN_BEHAVIOURS, NUM_TRAIN_BEHAVIOURS + NUM_TEST_BEHAVIOURS)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 777]))
    pairs = []
    for c in range(len(TABLE_CONFIGS)):
        shift = float(rng.uniform(0.5, 1.0)) if split == "ood" else 0.0
        pairs += [(c, b, shift) for b in held_out]
    return pairs


def task_plans(
    split: str, seed: int, cfg: NavConfig, train_behaviours: int = NUM_TRAIN_BEHAVIOURS
) -> list[Plan]:
    """The plans (endpoints, delays, speeds) behind `make_restaurant_tasks(split, seed, cfg)`."""
    behs = split_behaviours(split, seed)
    pairs = task_pairs(split, seed, train_behaviours)
    return [plan_task(behs[b], table_layout(c, s), cfg) for c, b, s in pairs]


def redraw_train_tasks(
    seed: int,
    cfg: NavConfig,
    task_ids: np.ndarray,
    stream: tuple[int, ...],
    train_behaviours: int = NUM_TRAIN_BEHAVIOURS,
) -> TaskParams:
    """Training tasks `task_ids` (indices into the training split) with fresh crowd behaviours.

    Extension `TrainConfig.redraw_behaviours`: each task keeps its table layout, and its six
    people get a behaviour drawn anew from the random stream `(seed, stream...)`, which is
    disjoint from the streams of the training, test and validation behaviours.
    """
    pairs = task_pairs("train", seed, train_behaviours)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 20231, 3, *stream]))
    tasks = []
    for i in np.asarray(task_ids).reshape(-1):
        config_index = pairs[int(i)][0]
        beh = sample_behaviour(rng, CrowdModel())
        tasks.append(build_task(table_layout(config_index), beh, cfg))
    return stack_params(tasks)


def make_restaurant_tasks(
    split: str, seed: int, cfg: NavConfig, train_behaviours: int = NUM_TRAIN_BEHAVIOURS
) -> TaskParams:
    """Stacked tasks of a split: train 8x15 = 120 (8 x train_behaviours), test 8x3 = 24,
    ood 8x3 = 24 (shifted tables), val 8x3 = 24 (three further held-out behaviours)."""
    behs = split_behaviours(split, seed)
    pairs = task_pairs(split, seed, train_behaviours)
    tasks = [build_task(table_layout(c, s), behs[b], cfg) for c, b, s in pairs]
    return stack_params(tasks)
