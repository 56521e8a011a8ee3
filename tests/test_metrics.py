"""method §8 metrics (SR, TT, CFR, SPL, MGD) against small hand-computed episodes."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax import metrics

F, T_ = False, True


def _episodes():
    """Four episodes of T = 4 steps; goal (0, 0) except episode C (shifted by (1, 1)).

    A: straight down 4 m, left 3 m into the goal, stays: success, P = 7, l = 5 - 0.5 = 4.5,
       in goal for 3 steps -> TT = 1, MGD = (9 + 0 + 0 + 0) / 4 = 2.25.
    B: collides on step 2, never reaches the goal: TT = 4, MGD = (25 + 25 + 16 + 16) / 4 = 20.5.
    C: collision-free, never reaches the goal: TT = 4, MGD = (18 + 13 + 10 + 9) / 4 = 12.5.
    D: straight line to the edge of the goal radius: P = l = 4.5 -> SPL = 1, TT = 1,
       MGD = (6.25 + 3 * 0.25) / 4 = 1.75.
    """
    pos = np.array(
        [
            [(3, 4), (3, 0), (0, 0), (0, 0), (0, 0)],
            [(3, 4), (3, 4), (3, 4), (0, 4), (0, 4)],
            [(4, 5), (4, 4), (4, 3), (4, 2), (4, 1)],
            [(3, 4), (1.5, 2), (0.3, 0.4), (0.3, 0.4), (0.3, 0.4)],
        ],
        dtype=np.float32,
    )
    collision = np.array([[F, F, F, F], [F, T_, F, F], [F, F, F, F], [F, F, F, F]])
    in_goal = np.array([[F, T_, T_, T_], [F, F, F, F], [F, F, F, F], [F, T_, T_, T_]])
    goal = np.array([(0, 0), (0, 0), (1, 1), (0, 0)], dtype=np.float32)
    return pos, collision, in_goal, goal


def test_per_episode_values():
    m = metrics.episode_metrics(*map(jnp.asarray, _episodes()))
    np.testing.assert_array_equal(m.success, [T_, F, F, T_])
    np.testing.assert_array_equal(m.collision_free, [T_, F, T_, T_])
    np.testing.assert_allclose(m.travel_time, [1, 4, 4, 1])
    np.testing.assert_allclose(m.spl, [4.5 / 7.0, 0.0, 0.0, 1.0], rtol=1e-6)
    np.testing.assert_allclose(m.mgd, [2.25, 20.5, 12.5, 1.75], rtol=1e-6)


def test_summary_over_tasks():
    out = metrics.compute(*map(jnp.asarray, _episodes()))
    assert set(out) == set(metrics.METRIC_NAMES)
    assert out["SR"] == pytest.approx(0.5)
    assert out["CFR"] == pytest.approx(0.75)
    assert out["TT"] == pytest.approx((1 + 4 + 4 + 1) / 4)
    assert out["SPL"] == pytest.approx((4.5 / 7.0 + 1.0) / 4, rel=1e-6)
    assert out["MGD"] == pytest.approx((2.25 + 20.5 + 12.5 + 1.75) / 4, rel=1e-6)


def test_robot_radius_enters_spl():
    pos, col, goal_in, goal = map(jnp.asarray, _episodes())
    m = metrics.episode_metrics(pos[:1], col[:1], goal_in[:1], goal[:1], robot_radius=0.5)
    np.testing.assert_allclose(m.spl, [(5.0 - 1.0) / 7.0], rtol=1e-6)


def test_batch_shape_is_kept():
    pos, col, goal_in, goal = _episodes()
    flat = metrics.episode_metrics(*map(jnp.asarray, (pos, col, goal_in, goal)))
    grid = metrics.episode_metrics(
        *map(jnp.asarray, (x.reshape((2, 2) + x.shape[1:]) for x in (pos, col, goal_in, goal)))
    )
    for a, b in zip(flat, grid, strict=True):
        assert b.shape == (2, 2)
        np.testing.assert_allclose(np.asarray(a), np.asarray(b).reshape(4))


def test_all_failures_and_all_successes():
    pos, col, goal_in, goal = _episodes()
    bad = metrics.compute(pos, np.ones_like(col), goal_in, goal)
    assert bad["SR"] == 0.0 and bad["CFR"] == 0.0 and bad["SPL"] == 0.0
    never = metrics.compute(pos, col, np.zeros_like(goal_in), goal)
    assert never["SR"] == 0.0 and never["TT"] == 4.0
