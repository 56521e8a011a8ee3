"""The synthetic sidewalk crowd: the default tasks when no data file is given (method §4)."""

from __future__ import annotations

import numpy as np
import pytest

from mpcpearl_jax.envs import make_tasks
from mpcpearl_jax.envs.numpy_ref import rounded_box_clearance
from mpcpearl_jax.envs.sidewalk import SIDEWALK_CONFIG, SyntheticCrowd, sidewalk_boxes
from mpcpearl_jax.envs.sidewalk.synthetic import reflect
from mpcpearl_jax.errors import ConfigError

CFG = SIDEWALK_CONFIG


@pytest.fixture(scope="module")
def train():
    tasks = make_tasks("sidewalk", "train", seed=0)
    return np.asarray(tasks.human_pos, np.float64), np.asarray(tasks.human_mask)


def _speeds(pos, mask):
    """Speeds [M] of people present on two consecutive steps."""
    v = np.linalg.norm(np.diff(pos, axis=1), axis=-1) / CFG.dt
    return v[mask[:, 1:] & mask[:, :-1]]


def test_default_split_sizes():
    for split, n in (("train", 25), ("test", 6), ("ood", 6)):
        tasks = make_tasks("sidewalk", split)
        assert tasks.human_pos.shape == (n, CFG.horizon + 1, 5, 2)
        assert tasks.human_mask.dtype == bool


def test_deterministic_per_seed():
    a = make_tasks("sidewalk", "test", seed=3)
    b = make_tasks("sidewalk", "test", seed=3)
    c = make_tasks("sidewalk", "test", seed=4)
    np.testing.assert_array_equal(np.asarray(a.human_pos), np.asarray(b.human_pos))
    np.testing.assert_array_equal(np.asarray(a.human_mask), np.asarray(b.human_mask))
    assert not np.allclose(np.asarray(a.human_pos), np.asarray(c.human_pos))
    train = make_tasks("sidewalk", "train", seed=3)
    assert not np.allclose(np.asarray(train.human_pos[:6]), np.asarray(a.human_pos))


def test_median_speed_is_the_zara_median(train):
    speeds = _speeds(*train)
    assert np.median(speeds) == pytest.approx(1.15, abs=0.07)
    assert 0.6 < speeds.min() and speeds.max() < 1.8  # no jumps at entry or exit


def test_people_walk_both_ways_with_lateral_drift(train):
    pos, mask = train
    both = mask[:, 1:] & mask[:, :-1]
    vx = np.diff(pos[..., 0], axis=1)[both] / CFG.dt
    vy = np.diff(pos[..., 1], axis=1)[both] / CFG.dt
    assert (vx > 0.5).mean() > 0.25 and (vx < -0.5).mean() > 0.25
    assert np.std(vy) > 0.03 and np.abs(vy).max() < 0.5


def test_people_stay_on_the_sidewalk(train):
    pos, mask = train
    lo, hi, rad = sidewalk_boxes(CFG)
    pts = pos[mask]
    clear = np.stack(
        [
            rounded_box_clearance(p, lo.astype(float), hi.astype(float), rad)
            for p in pts[:: max(1, len(pts) // 4000)]
        ]
    )
    assert clear.min() >= CFG.human_radius  # the whole body stays off the road and the boxes
    assert pts[:, 0].min() >= CFG.arena_lo[0] and pts[:, 0].max() <= CFG.arena_hi[0]


def test_presence_varies_as_people_enter_and_leave(train):
    _, mask = train
    changes = np.diff(mask.astype(int), axis=1)
    assert (changes == 1).sum() > 10 and (changes == -1).sum() > 10
    in_view = mask.sum(axis=-1)  # [N, T + 1]
    assert 3 <= np.median(in_view) <= 5


def test_ood_crowd_is_faster():
    ood = make_tasks("sidewalk", "ood")
    speeds = _speeds(np.asarray(ood.human_pos, np.float64), np.asarray(ood.human_mask))
    assert np.median(speeds) > 1.35


def test_reflect_folds_into_band():
    y = np.array([2.0, 3.0, 5.5, 8.5, -1.0])
    np.testing.assert_allclose(reflect(y, 2.0, 5.0), [2.0, 3.0, 4.5, 2.5, 5.0])


def test_crowd_config_is_validated():
    with pytest.raises(ConfigError, match="SyntheticCrowd.candidates"):
        SyntheticCrowd(candidates=0)
    with pytest.raises(ConfigError, match="SyntheticCrowd.lane_hi"):
        SyntheticCrowd(lane_lo=5.0, lane_hi=3.0)
