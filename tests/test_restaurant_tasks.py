"""Restaurant task sets (SPEC 3): sizes, structure, determinism and the crowd's invariants."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.envs.restaurant.generator import (
    NUM_TRAIN_BEHAVIOURS,
    TABLE_CONFIGS,
    TABLE_RADIUS,
    CrowdModel,
    behaviours,
    table_layout,
)

CFG = make_env("restaurant").config
SPLITS = ("train", "test", "ood")
INVARIANT_SPLITS = (*SPLITS, "ood@3")  # the crowd invariants also on another seed


def _numpy_tasks(split, seed):
    return jax.tree_util.tree_map(np.asarray, make_tasks("restaurant", split, seed=seed))


@pytest.fixture(scope="module")
def tasks():
    """{split: TaskParams as NumPy} for seed 0, plus "ood@3": the ood split of seed 3."""
    out = {s: _numpy_tasks(s, 0) for s in SPLITS}
    out["ood@3"] = _numpy_tasks("ood", 3)
    return out


def test_sizes_and_shapes(tasks):
    sizes = {"train": 120, "test": 24, "ood": 24, "ood@3": 24}
    for split, p in tasks.items():
        n = sizes[split]
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


def _delays(split):
    split, _, seed = split.partition("@")
    behs = behaviours(int(seed or 0))
    if split == "train":
        return np.stack([behs[k % NUM_TRAIN_BEHAVIOURS].delay for k in range(120)])
    return np.stack([behs[NUM_TRAIN_BEHAVIOURS + k % 3].delay for k in range(24)])


@pytest.mark.parametrize("split", INVARIANT_SPLITS)
def test_people_still_before_their_delay(tasks, split):
    hp = tasks[split].human_pos
    delays = _delays(split)
    assert delays.max() > 5  # the check below is not vacuous
    for k in range(hp.shape[0]):
        for h in range(hp.shape[2]):
            d = delays[k, h]
            waiting = hp[k, : d + 1, h] - hp[k, 0, h]
            np.testing.assert_allclose(waiting, 0.0, atol=1e-5, err_msg=f"task {k} person {h}")
            assert np.linalg.norm(hp[k, -1, h] - hp[k, 0, h]) > 0.5  # and then they walk
