"""The SQP run to convergence and its extra starts (`mpc.sqp_iters`, `sqp_step_tol`,
`multi_start`), on problems recorded from training (tests/data/mpc_problems.npz)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.mpc import MPCConfig, SQPSolver
from mpcpearl_jax.mpc.problem import SQP_STOPS, START_NAMES, merit, starts
from mpcpearl_jax.mpc.qp_osqp import OSQPSettings
from mpcpearl_jax.mpc.recorded import load
from tests.test_mpc_model import _row_problem

PICK = (3, 150, 420, 700, 1010)  # recorded problems, spread over the recording
QP = OSQPSettings.from_config(MPCConfig())


@pytest.fixture(scope="module")
def recorded():
    rec = load(Path(__file__).parent / "data" / "mpc_problems.npz")
    base = dataclasses.replace(rec.params, unsafe_recovery=False)
    assert rec.qp == QP  # recorded under the default QP settings
    return base, [rec.row(i) for i in PICK]


def _solve(base, row, init, **fields):
    return SQPSolver(dataclasses.replace(base, **fields), QP).solve(row, init)


def test_more_iterations_never_raise_the_exact_merit(recorded):
    """Every accepted step lowers the exact SAA merit, so the plan after n + k QPs is at least as
    good as after n (the same iterates, continued); the cap's result is the best iterate."""
    base, rows = recorded
    for row, init in rows:
        m = [_solve(base, row, init, sqp_iters=n, sqp_step_tol=0.0).merit for n in (1, 2, 5, 30)]
        assert all(b <= a + 1e-9 for a, b in zip(m, m[1:], strict=False)), m
        res = _solve(base, row, init, sqp_iters=30, sqp_step_tol=0.0)
        # the returned merit is the plan's own exact merit
        assert res.merit == pytest.approx(merit(base, row, res.u, res.poses))
        assert res.stop in SQP_STOPS and res.start in START_NAMES


def test_converged_sqp_ends_by_its_tolerance_or_a_stall_not_the_cap(recorded):
    base, rows = recorded
    for row, init in rows:
        res = _solve(base, row, init, sqp_iters=100, sqp_step_tol=1e-4)
        assert res.stop in ("converged", "stalled"), res.stop
        assert res.n_qp < 100
        capped = _solve(base, row, init, sqp_iters=1, sqp_step_tol=0.0)
        assert capped.stop in ("capped", "stalled", "qp_failed")
        assert capped.n_qp == 1


def test_multi_start_keeps_the_lowest_merit_safe_plan(recorded):
    """ "always": the SQP from every start (warm, cold, standing still); the safe plan of lowest
    merit is kept, so it is never worse than the first start's safe plan."""
    base, rows = recorded
    for row, init in rows:
        fields = dict(sqp_iters=10, sqp_step_tol=1e-3)
        one = _solve(base, row, init, **fields)
        many = _solve(base, row, init, multi_start="always", **fields)
        each = [
            _solve(base, row, u, **fields) for _, u in starts(base, row, init)
        ]  # each start alone (cold start where u is the cold plan: the same SQP)
        safe = [r.merit for r in each if r.ok]
        if safe:
            assert many.ok and many.merit == pytest.approx(min(safe))
        if one.ok:
            assert many.merit <= one.merit + 1e-9
        assert many.n_qp == sum(r.n_qp for r in each)


def test_restart_on_failure_changes_nothing_where_the_first_start_is_safe(recorded):
    base, rows = recorded
    for row, init in rows:
        fields = dict(sqp_iters=5, sqp_step_tol=1e-3)
        one = _solve(base, row, init, **fields)
        again = _solve(base, row, init, multi_start="on_failure", **fields)
        if one.ok:
            np.testing.assert_array_equal(one.u, again.u)
            assert again.n_qp == one.n_qp


def test_every_start_unsafe_falls_back_as_a_single_start():
    """A person on the robot in every sample: no start gives a safe first stage; the result is
    the first start's, not ok, and the caller falls back as without multi-start."""
    row = _row_problem()
    samples = np.broadcast_to(row.x0[:2], row.samples.shape).copy()
    row = row._replace(samples=samples)
    params = _params(multi_start="always")
    res = SQPSolver(params, QP).solve(row, None)
    single = SQPSolver(_params(), QP).solve(row, None)
    assert not res.ok and res.reason == "unsafe"
    assert res.start == single.start == "cold"
    np.testing.assert_array_equal(res.u, single.u)
    assert res.n_qp > single.n_qp  # the other starts ran


def _params(**fields):
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import solver_params

    cfg = MPCConfig(sqp_iters=5, sqp_step_tol=1e-3, **fields)
    return solver_params(cfg, make_env("restaurant").config, 2)


@pytest.mark.parametrize(
    "fields, name",
    [
        ({"sqp_iters": 0}, "sqp_iters"),
        ({"sqp_iters": 5000}, "sqp_iters"),
        ({"sqp_iters": 2.5}, "sqp_iters"),
        ({"sqp_step_tol": -1.0}, "sqp_step_tol"),
        ({"sqp_step_tol": float("nan")}, "sqp_step_tol"),
        ({"sqp_step_tol": float("inf")}, "sqp_step_tol"),
        ({"sqp_step_tol": 3.0}, "sqp_step_tol"),
        ({"multi_start": "sometimes"}, "multi_start"),
    ],
)
def test_out_of_range_sqp_settings_are_one_line_errors(fields, name):
    with pytest.raises(ConfigError) as e:
        MPCConfig(**fields)
    msg = str(e.value)
    assert name in msg and "\n" not in msg
