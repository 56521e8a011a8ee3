"""method §8 metrics (SR, TT, CFR, SPL, MGD) against small hand-computed episodes."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.evaluation import metrics

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


def test_one_table_names_orders_directs_and_formats_the_metrics():
    """`metrics.METRICS`: the paper's five metrics in its order, each the mean of one
    `EpisodeMetrics` field, lower better for TT and MGD only; the evaluator's summary, the
    per-task scoring and the tables read it."""
    from lab.tables import render, statistics
    from mpcpearl_jax.evaluation.report import metrics_table

    assert metrics.METRIC_NAMES == ("SR", "TT", "CFR", "SPL", "MGD")
    assert {m.field for m in metrics.METRICS.values()} <= set(metrics.EpisodeMetrics._fields)
    assert metrics.LOWER_IS_BETTER == {"TT", "MGD"}
    assert statistics.LOWER_IS_BETTER == {"TT", "MGD", "first_success_min"}
    assert statistics.seed_stats([1.0, 3.0], "TT")[2] == 3.0  # the worst TT is the largest
    assert statistics.seed_stats([1.0, 3.0], "SPL")[2] == 1.0
    m = metrics.episode_metrics(*map(jnp.asarray, _episodes()))
    values = metrics.metric_values(m)
    assert tuple(values) == metrics.METRIC_NAMES
    np.testing.assert_array_equal(values["CFR"], m.collision_free)
    assert metrics.format_metric("TT", 2.5) == "2.50" and render.METRICS == metrics.METRIC_NAMES
    table = metrics_table([("run", {"SR": 0.5, "MGD": 12.345})])
    assert "| SR | 0.50 |" in table and "| MGD | 12.35 |" in table and "| TT | - |" in table


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


def _first_contact_numpy(pos, col, goal_in, task, r_r, r_d):
    """Loop reference of `metrics.first_contact` for one episode."""
    hits = [t for t in range(col.shape[0]) if col[t]]
    if not hits:
        return -1, False, 0, False
    t = hits[0]
    p = pos[t]
    person = min(
        (
            float(np.hypot(*(task.human_pos[t + 1, h] - p))) - (r_r + r_d)
            for h in range(task.human_pos.shape[1])
            if task.human_mask[t + 1, h]
        ),
        default=np.inf,
    )
    static = np.inf
    for lo, hi, rad in zip(task.static_lo, task.static_hi, task.static_radius, strict=True):
        gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        static = min(static, float(np.hypot(*gap)) - rad - r_r)
    reached_after = any(goal_in[s] for s in range(t + 1, col.shape[0]))
    return t, person < static, len(hits), reached_after


def test_first_contact_against_a_numpy_loop():
    """Random positions near the people and tables of real restaurant tasks, random contact and
    goal flags (some episodes without contact): step, obstacle kind, contact count and 'goal
    reached after' match a loop reference; both obstacle kinds occur."""
    import jax

    from mpcpearl_jax.envs import make_tasks

    tasks = make_tasks("restaurant", "train", 0)
    rng = np.random.default_rng(3)
    n, horizon = 60, 80
    idx = rng.integers(0, 120, n)
    batch = jax.tree_util.tree_map(lambda x: np.asarray(x)[idx], tasks)
    pos = rng.uniform(-4.5, 4.5, (n, horizon + 1, 2)).astype(np.float32)
    for i in range(n):  # put the robot next to a person or a table centre at some steps
        for t in rng.integers(0, horizon, 10):
            if rng.random() < 0.5:
                near = batch.human_pos[i, t + 1, rng.integers(6)]
            else:
                s = rng.integers(batch.static_lo.shape[1])
                near = 0.5 * (batch.static_lo[i, s] + batch.static_hi[i, s])
            pos[i, t] = near + rng.normal(0.0, 0.4, 2)
    col = rng.random((n, horizon)) < 0.03
    col[: n // 5] = False
    goal_in = rng.random((n, horizon)) < 0.05
    contact = jax.vmap(lambda p, c, g, k: metrics.first_contact(p, c, g, k, 0.25, 0.25))
    got = contact(jnp.asarray(pos), jnp.asarray(col), jnp.asarray(goal_in), batch)
    kinds = set()
    for i in range(n):
        task = jax.tree_util.tree_map(lambda x, i=i: np.asarray(x)[i], batch)
        want = _first_contact_numpy(pos[i], col[i], goal_in[i], task, 0.25, 0.25)
        assert int(got.step[i]) == want[0]
        assert bool(got.with_person[i]) == want[1]
        assert int(got.steps_in_contact[i]) == want[2]
        assert bool(got.reached_after[i]) == want[3]
        if want[0] >= 0:
            kinds.add(want[1])
    assert kinds == {True, False}
    assert int(jnp.sum(got.step < 0)) >= n // 5
