"""The device SQP (`mpc.solver = "device"`) against the host SQP on OSQP, its reference.

The gate's data, `tests/data/mpc_problems.npz`, holds SQP problems recorded from fired rows of a
real `cpu-explore` training on the restaurant tasks (eps 0.2) with their warm-start plans, and
OSQP's first input and reason on each (`experiments.diagnostics.record_mpc_problems`). The fast
test checks a fixed subset; the whole file is the slow test's. Both require the device solver's
first input within 0.02 normalized action units of OSQP's on >= 99 % of the problems, and the
same decision (solved / least violation / unsafe or failed, i.e. fallback) on >= 98 %.
"""

from __future__ import annotations

from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.diagnostics.record_mpc_problems import regenerate, solver_params_of
from mpcpearl_jax.envs.dynamics import to_normalized
from mpcpearl_jax.mpc import device_solver as ds
from mpcpearl_jax.mpc.solver import RowProblem

FILE = Path(__file__).parent / "data" / "mpc_problems.npz"
FAST_ROWS = 64
V_MAX_ENV = 5.0  # restaurant's v_max: the normalization of the actions


def _decision(reason) -> np.ndarray:
    """0 solved, 1 least violation, 2 fallback (unsafe, QP failed, non-finite)."""
    reason = np.asarray(reason)
    return np.where(reason == "solved", 0, np.where(reason == "least_violation", 1, 2))


@pytest.fixture(scope="module")
def data():
    with np.load(FILE) as f:
        return {k: f[k] for k in f.files}


def _solve(data, rows: np.ndarray, chunk: int = 64):
    p = solver_params_of(data)
    solve = jax.jit(ds.make_batch_solver(p, 30))
    probs = regenerate({k: v[rows] for k, v in data.items() if k != "params"}, p.num_samples)
    first, reason = [], []
    for i in range(0, rows.size, chunk):
        part = jax.tree_util.tree_map(lambda a, i=i: jnp.asarray(a[i : i + chunk]), probs)
        sl = slice(i, i + chunk)
        res = solve(
            part, jnp.asarray(data["u_init"][rows][sl]), jnp.asarray(data["has_init"][rows][sl])
        )
        first.append(np.asarray(res.u[:, 0]))
        reason.extend(ds.REASONS[int(r)] for r in np.asarray(res.reason))
    return np.concatenate(first), np.asarray(reason)


def _gate(data, rows):
    first, reason = _solve(data, rows)
    ref = data["osqp_first"][rows]
    gap = np.max(
        np.abs(np.asarray(to_normalized(first, V_MAX_ENV) - to_normalized(ref, V_MAX_ENV))), axis=1
    )
    same = _decision(reason) == _decision(data["osqp_reason"][rows])
    return float(np.mean(gap <= 0.02)), float(np.mean(same))


def test_the_gate_data_is_from_training_and_small(data):
    assert data["x0"].shape[0] >= 1000
    assert FILE.stat().st_size < 3e6
    assert data["has_init"].any() and not data["has_init"].all()  # warm and cold starts
    assert "solved" in set(np.unique(data["osqp_reason"]))


def test_device_first_action_and_decision_match_osqp_on_a_subset(data):
    rows = np.linspace(0, data["x0"].shape[0] - 1, FAST_ROWS).round().astype(int)
    close, same = _gate(data, rows)
    assert close >= 0.99 - 1.0 / FAST_ROWS, f"first action within 0.02 on {close:.1%}"
    assert same >= 0.98 - 1.0 / FAST_ROWS, f"same decision on {same:.1%}"


@pytest.mark.slow
def test_device_first_action_and_decision_match_osqp_on_every_recorded_problem(data):
    close, same = _gate(data, np.arange(data["x0"].shape[0]))
    print(f"first action within 0.02: {close:.2%}; same decision: {same:.2%}")
    assert close >= 0.99, f"first action within 0.02 on {close:.1%}"
    assert same >= 0.98, f"same decision on {same:.1%}"


def test_a_nan_problem_is_not_ok_and_never_gives_a_finite_looking_plan(data):
    p = solver_params_of(data)
    probs = regenerate({k: v[:4] for k, v in data.items() if k != "params"}, p.num_samples)
    samples = probs.samples.copy()
    samples[1] = np.nan
    x0 = probs.x0.copy()
    x0[2] = np.nan
    bad = probs._replace(samples=samples, x0=x0)
    res = jax.jit(ds.make_batch_solver(p, 30))(
        jax.tree_util.tree_map(jnp.asarray, bad),
        jnp.asarray(data["u_init"][:4]),
        jnp.asarray(data["has_init"][:4]),
    )
    ok = np.asarray(res.ok)
    assert not ok[1] and not ok[2]
    assert ds.REASONS[int(res.reason[2])] in ("nonfinite", "qp_failed", "unsafe")


def test_the_batched_solve_compiles_once(data):
    p = solver_params_of(data)
    probs = regenerate({k: v[:8] for k, v in data.items() if k != "params"}, p.num_samples)
    solve = ds.make_batch_solver(p, 5)
    traced = jax.jit(chex.assert_max_traces(solve, n=1))
    for i in range(3):
        part = jax.tree_util.tree_map(lambda a, i=i: jnp.asarray(a[2 * i : 2 * i + 2]), probs)
        traced(part, jnp.asarray(data["u_init"][:2]), jnp.asarray(data["has_init"][:2]))


def test_model_and_merit_equal_the_host_solver(data):
    from mpcpearl_jax.mpc import model
    from mpcpearl_jax.mpc import solver as host

    p = solver_params_of(data)
    probs = regenerate({k: v[:3] for k, v in data.items() if k != "params"}, p.num_samples)
    for i in range(3):
        row = RowProblem(*(np.asarray(a[i]) for a in probs))
        row64 = RowProblem(*(a.astype(np.float64) if a.dtype.kind == "f" else a for a in row))
        u = host.clip_inputs(p, host.cold_start(p, row64) + 0.1 * i)
        xs = model.rollout(row64.x0, u, p.dt, p.wheelbase)
        xs_d = ds.rollout(p, jnp.asarray(row.x0), jnp.asarray(u, jnp.float32))
        np.testing.assert_allclose(np.asarray(xs_d), xs, atol=1e-4)
        a, b = model.linearize(xs[:-1], u, p.dt, p.wheelbase)
        a_d, b_d = ds.jacobians(p, jnp.asarray(xs[:-1], jnp.float32), jnp.asarray(u, jnp.float32))
        np.testing.assert_allclose(np.asarray(a_d), a, atol=1e-5)
        np.testing.assert_allclose(np.asarray(b_d), b, atol=1e-5)
        row_d = jax.tree_util.tree_map(jnp.asarray, row)
        got = float(ds.merit(p, row_d, jnp.asarray(u, jnp.float32), xs_d))
        assert got == pytest.approx(host.merit(p, row64, u, xs), rel=1e-4, abs=1e-2)
