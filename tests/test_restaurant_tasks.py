"""Restaurant task sets (paper Sec. IV-A): sizes, structure, determinism and the crowd's motion."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.envs.restaurant.generator import (
    LANDMARKS,
    ROUTES,
    TABLE_CONFIGS,
    TABLE_RADIUS,
    CrowdModel,
    split_behaviours,
    table_layout,
    task_pairs,
    task_plans,
)

CFG = make_env("restaurant").config
SPLITS = ("train", "test", "ood", "val")
INVARIANT_SPLITS = (*SPLITS, "train@3", "test@3", "ood@3")  # the crowd also on another seed


def _numpy_tasks(split, seed):
    return jax.tree_util.tree_map(np.asarray, make_tasks("restaurant", split, seed=seed))


@pytest.fixture(scope="module")
def tasks():
    """{split: TaskParams as NumPy} for seed 0, plus "split@3": the splits of seed 3."""
    out = {s: _numpy_tasks(s, 0) for s in SPLITS}
    out.update({f"{s}@3": _numpy_tasks(s, 3) for s in SPLITS})
    return out


@functools.cache
def _plans(split):
    """The plans (endpoints, delays, speeds) behind the tasks of `split` ("name" or "name@seed")."""
    split, _, seed = split.partition("@")
    return task_plans(split, int(seed or 0), CFG)


def test_sizes_and_shapes(tasks):
    sizes = {"train": 120, "test": 24, "ood": 24, "val": 24}
    for split, p in tasks.items():
        n = sizes[split.partition("@")[0]]
        assert p.human_pos.shape == (n, CFG.horizon + 1, 6, 2)
        assert p.human_mask.shape == (n, CFG.horizon + 1, 6) and p.human_mask.all()
        assert p.static_lo.shape == p.static_hi.shape == (n, 5, 2)
        np.testing.assert_array_equal(p.static_lo, p.static_hi)  # round tables
        np.testing.assert_array_equal(p.static_radius, np.full((n, 5), TABLE_RADIUS))
        np.testing.assert_allclose(p.start, np.tile([-4.5, 4.5, -np.pi / 8], (n, 1)), atol=1e-6)
        np.testing.assert_allclose(p.goal, np.tile([3.5, -3.5], (n, 1)))


def test_train_is_8_configurations_by_15_behaviours(tasks):
    p = tasks["train"]
    assert len(TABLE_CONFIGS) == 8 and len(set(TABLE_CONFIGS)) == 8
    for c in range(8):
        block = slice(15 * c, 15 * (c + 1))
        np.testing.assert_allclose(p.static_lo[block], np.broadcast_to(table_layout(c), (15, 5, 2)))
        paths = p.human_pos[block].reshape(15, -1)
        assert len({row.tobytes() for row in paths}) == 15  # 15 different behaviours
    # neither the start nor the goal lies inside a table's safety zone
    centres = p.static_lo.reshape(-1, 2)
    zone = TABLE_RADIUS + CFG.robot_radius + CFG.r_safe
    assert np.min(np.linalg.norm(centres - p.goal[0], axis=-1)) > zone
    assert np.min(np.linalg.norm(centres - p.start[0, :2], axis=-1)) > zone


def test_test_tasks_are_held_out_behaviours_on_the_same_tables(tasks):
    train, test = tasks["train"], tasks["test"]
    for c in range(8):
        layouts = test.static_lo[3 * c : 3 * (c + 1)]
        np.testing.assert_allclose(layouts, np.broadcast_to(table_layout(c), (3, 5, 2)))
        seen = {row.tobytes() for row in train.human_pos[15 * c : 15 * (c + 1)].reshape(15, -1)}
        for row in test.human_pos[3 * c : 3 * (c + 1)].reshape(3, -1):
            assert row.tobytes() not in seen


def test_val_tasks_are_other_held_out_behaviours_on_the_same_tables(tasks):
    train, test, val = tasks["train"], tasks["test"], tasks["val"]
    for c in range(8):
        np.testing.assert_allclose(
            val.static_lo[3 * c : 3 * (c + 1)], np.broadcast_to(table_layout(c), (3, 5, 2))
        )
        seen = {row.tobytes() for row in train.human_pos[15 * c : 15 * (c + 1)].reshape(15, -1)}
        seen |= {row.tobytes() for row in test.human_pos[3 * c : 3 * (c + 1)].reshape(3, -1)}
        for row in val.human_pos[3 * c : 3 * (c + 1)].reshape(3, -1):
            assert row.tobytes() not in seen


def test_fewer_training_behaviours_are_the_first_of_the_papers_and_more_are_refused(tasks):
    fewer = jax.tree_util.tree_map(
        np.asarray, make_tasks("restaurant", "train", seed=0, train_behaviours=4)
    )
    assert fewer.human_pos.shape[0] == 8 * 4
    paths = tasks["train"].human_pos.reshape(8, 15, -1)
    np.testing.assert_array_equal(fewer.human_pos.reshape(8, 4, -1), paths[:, :4])
    for bad in (0, 16, 40, True, 2.0):  # more than 15 per layout was an extension, removed
        with pytest.raises(ValueError, match="train_behaviours"):
            make_tasks("restaurant", "train", seed=0, train_behaviours=bad)
    with pytest.raises(TypeError, match="nosuch"):
        make_tasks("restaurant", "train", seed=0, nosuch=1)


def test_ood_tables_shifted_left(tasks):
    shift = tasks["test"].static_lo - tasks["ood"].static_lo  # [24, 5, 2]
    np.testing.assert_allclose(shift[..., 1], 0.0)
    assert np.all(shift[..., 0] >= 0.5 - 1e-6) and np.all(shift[..., 0] <= 1.0 + 1e-6)
    # one shift per configuration (all its tables move together), not all the same
    per_task = shift[..., 0]
    np.testing.assert_allclose(per_task, per_task[:, :1] * np.ones((1, 5)), atol=1e-6)
    assert np.ptp(per_task[:, 0]) > 0.05


def test_deterministic_for_a_seed_and_different_across_seeds(tasks):
    again = make_tasks("restaurant", "test", seed=0)
    for a, b in zip(
        jax.tree_util.tree_leaves(tasks["test"]), jax.tree_util.tree_leaves(again), strict=True
    ):
        np.testing.assert_array_equal(a, np.asarray(b))
    other = make_tasks("restaurant", "test", seed=1)
    assert not np.allclose(tasks["test"].human_pos, np.asarray(other.human_pos))


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_people_never_inside_a_table(tasks, split):
    p = tasks[split]
    d = np.linalg.norm(p.human_pos[:, :, :, None, :] - p.static_lo[:, None, None], axis=-1)
    assert d.min() >= TABLE_RADIUS + CFG.human_radius - 1e-5


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_people_never_overlap(tasks, split):
    hp = tasks[split].human_pos
    d = np.linalg.norm(hp[:, :, :, None] - hp[:, :, None], axis=-1)
    d += np.eye(hp.shape[2]) * 1e3
    assert d.min() >= 2 * CFG.human_radius - 1e-5


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_people_stay_in_the_arena(tasks, split):
    hp = tasks[split].human_pos
    lo = np.asarray(CFG.arena_lo) + CFG.human_radius
    hi = np.asarray(CFG.arena_hi) - CFG.human_radius
    assert np.all(hp >= lo - 1e-6) and np.all(hp <= hi + 1e-6)


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_walking_speed_about_3_m_per_s(tasks, split):
    hp = tasks[split].human_pos
    speed = np.linalg.norm(np.diff(hp, axis=1), axis=-1) / CFG.dt  # [N, T, H]
    walking = speed[speed > 0.5]
    assert 2.8 <= np.median(walking) <= 3.6
    assert speed.max() <= 1.1 * CrowdModel().speed_range[1]
    # people do walk: most cover several metres
    travelled = np.sum(speed * CFG.dt, axis=1)
    assert np.mean(travelled > 3.0) > 0.8


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_people_still_before_their_delay(tasks, split):
    hp = tasks[split].human_pos
    delays = np.stack([plan.delay for plan in _plans(split)])  # [N, H]
    assert delays.max() > 5  # the check below is not vacuous
    waiting = np.arange(hp.shape[1])[None, :, None] <= delays[:, None, :]  # [N, T + 1, H]
    moved = np.linalg.norm(hp - hp[:, :1], axis=-1)
    assert np.all(moved[waiting] < 1e-5)
    assert np.all(moved[:, -1] > 0.5)  # and then they walk


def _moves(hp):
    """[N, T, H] bool: who moves (more than float noise) in each step."""
    return np.linalg.norm(np.diff(hp, axis=1), axis=-1) > 1e-5


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_people_walk_in_the_first_half_then_stand(tasks, split):
    """As in the authors' scenarios: people walk for roughly the first 36 of the 80 steps."""
    moves = _moves(tasks[split].human_pos)
    assert np.mean(moves[:, 45:].any(axis=1)) < 0.10  # still moving after step 45
    last = moves.shape[1] - 1 - np.argmax(moves[:, ::-1], axis=1)  # last step with a move
    assert moves.any(axis=1).all() and 25 <= np.median(last) <= 45


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_mean_walking_speed_in_authors_range(tasks, split):
    hp = tasks[split].human_pos
    speed = np.linalg.norm(np.diff(hp, axis=1), axis=-1) / CFG.dt  # [N, T, H]
    lo, hi = CrowdModel().speed_range
    assert lo <= np.mean(speed[_moves(hp)]) <= hi
    # the planned speeds are in the range as well
    speeds = np.stack([plan.speed for plan in _plans(split)])
    assert np.all((speeds >= lo - 1e-6) & (speeds <= hi + 1e-6))


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_people_end_at_their_goal_and_stay(tasks, split):
    hp = tasks[split].human_pos
    goals = np.stack([plan.goal for plan in _plans(split)])  # [N, H, 2]
    err = np.linalg.norm(hp - goals[:, None], axis=-1)  # [N, T + 1, H]
    assert np.all(err[:, -1] < 0.3)  # every person ends near the intended goal ...
    at_goal = err < 1e-6
    assert np.mean(at_goal[:, -1]) >= 0.99  # ... and (nearly) all exactly on it
    # once on the goal a person stands there for the rest of the episode
    arrived = np.maximum.accumulate(at_goal, axis=1)
    assert np.array_equal(arrived, at_goal)
    # standing people stay out of each other's way: goals are apart by at least 2 r_d + 0.5
    d = np.linalg.norm(goals[:, :, None] - goals[:, None], axis=-1) + np.eye(goals.shape[1]) * 1e3
    assert d.min() >= 2 * CFG.human_radius + CrowdModel().goal_gap - 1e-5


@pytest.mark.parametrize("split", SPLITS)
def test_endpoints_are_seats_and_landmarks(split):
    behs = split_behaviours(split, 0)
    model = CrowdModel()
    seat = TABLE_RADIUS + CFG.human_radius + model.seat_gap
    for (c, b, shift), plan in zip(task_pairs(split, 0), _plans(split), strict=True):
        tables = table_layout(c, shift)
        for h, r in enumerate(behs[b].route):
            for name, pt in zip(ROUTES[r], (plan.start[h], plan.goal[h]), strict=True):
                d = np.linalg.norm(tables - pt, axis=-1)
                if name == "table":  # a seat just off a table edge
                    np.testing.assert_allclose(d.min(), seat, atol=1e-5)
                else:  # a point near the landmark, clear of the tables
                    assert d.min() >= seat - 1e-5
                    assert np.linalg.norm(pt - LANDMARKS[name]) < 4 * model.landmark_jitter


def test_redrawn_tasks_keep_the_layout_and_change_the_crowd_deterministically():
    from mpcpearl_jax.envs import make_env, make_tasks, redraw_tasks

    cfg = make_env("restaurant").config
    train = make_tasks("restaurant", "train", 0, config=cfg)
    ids = np.array([0, 17, 119])
    a = redraw_tasks("restaurant", 0, ids, (0, 5), config=cfg)
    b = redraw_tasks("restaurant", 0, ids, (0, 5), config=cfg)
    c = redraw_tasks("restaurant", 0, ids, (0, 6), config=cfg)
    orig = jax.tree_util.tree_map(lambda x: np.asarray(x)[ids], train)
    np.testing.assert_array_equal(np.asarray(a.static_lo), orig.static_lo)  # same tables
    np.testing.assert_array_equal(np.asarray(a.start), orig.start)
    np.testing.assert_array_equal(np.asarray(a.goal), orig.goal)
    np.testing.assert_array_equal(np.asarray(a.human_pos), np.asarray(b.human_pos))
    assert not np.allclose(np.asarray(a.human_pos), np.asarray(c.human_pos))
    assert not np.allclose(np.asarray(a.human_pos), orig.human_pos)
    # the redrawn crowd obeys the crowd model: nobody inside a table, people stand at the end
    pos, tables = np.asarray(a.human_pos), np.asarray(a.static_lo)
    d = np.linalg.norm(pos[:, :, :, None, :] - tables[:, None, None, :, :], axis=-1)
    assert d.min() > 0.5
    np.testing.assert_allclose(pos[:, -1], pos[:, -5], atol=1e-5)


def _old_idiom(cfg, split, config, seed=None):
    """The task set as the commands built it before `envs.tasks_for`."""
    kw = {"data": cfg.data} if cfg.data else {}
    kw.update(cfg.task_options)
    seed = cfg.task_seed if seed is None else seed
    return make_tasks(cfg.env, split, seed, config=config, **kw)


def _same(a, b):
    jax.tree_util.tree_map(np.testing.assert_array_equal, a, b)


def test_tasks_for_a_run_config_are_the_old_idiom_s():
    """`envs.tasks_for`: the run's family, task seed, task options and env overrides; the
    validation set (`envs.validation_tasks`) is the family's val split."""
    from mpcpearl_jax.config import ExperimentConfig
    from mpcpearl_jax.envs import VAL_TASKS, tasks_for, validation_tasks

    cfg = ExperimentConfig(
        task_seed=2, task_options={"train_behaviours": 4}, env_overrides={"observe_time": True}
    )
    config = make_env("restaurant", observe_time=True).config
    for split in ("train", "test", "val"):
        _same(tasks_for(cfg, split), _old_idiom(cfg, split, config))
    _same(tasks_for(cfg, "ood", config=CFG, seed=5), _old_idiom(cfg, "ood", CFG, seed=5))
    val, what = validation_tasks(cfg)
    _same(val, _old_idiom(cfg, "val", config))
    assert "'val' split" in what and VAL_TASKS == 24
