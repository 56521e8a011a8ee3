"""The device SQP (`mpc.solver = "device"`) against the host SQP on OSQP, its reference.

The gate's data, `tests/data/mpc_problems.npz`, holds SQP problems recorded from fired rows of a
real `cpu-explore` training on the restaurant tasks (eps 0.2) with their warm-start plans, and
OSQP's first input and reason on each (`benchmarks.record_mpc_problems`). The gate
requires the device solver's first input within 0.02 normalized action units of OSQP's on >= 99 %
of the problems, and the same decision (solved / least violation / fallback) on >= 98 %.

On a 2-core CPU the device solver compiles in about a minute and solves a row in seconds, so the
tests that run it are slow. The gate does not hold yet (docs/method.md §6): on 48 of the recorded
problems the first input was within 0.02 on 50 % and the decision equal on 96 %; OSQP at its
configured tolerance (1e-3, 200 iterations) itself moves its first input by more than 0.02 on 8
of 16 problems when solved to 1e-6, so the gate's tolerance is below the reference's own
accuracy. The gate tests are therefore strict expected failures: they fail the day the gate
holds, so that the mark is removed then.
"""

from __future__ import annotations

from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.record_mpc_problems import regenerate, solver_params_of
from mpcpearl_jax.envs.dynamics import to_normalized
from mpcpearl_jax.mpc import device_solver as ds
from mpcpearl_jax.mpc.solver import RowProblem

FILE = Path(__file__).parent / "data" / "mpc_problems.npz"
FAST_ROWS = 48
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


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="gate not met: 50 % within 0.02 on 48 problems")
def test_device_first_action_and_decision_match_osqp_on_a_subset(data):
    rows = np.linspace(0, data["x0"].shape[0] - 1, FAST_ROWS).round().astype(int)
    close, same = _gate(data, rows)
    assert close >= 0.99 - 1.0 / FAST_ROWS, f"first action within 0.02 on {close:.1%}"
    assert same >= 0.98 - 1.0 / FAST_ROWS, f"same decision on {same:.1%}"


@pytest.mark.slow
@pytest.mark.skipif(
    jax.default_backend() == "cpu",
    reason="about 20 min on a 2-core CPU; on a GPU (about 1 s): python -m benchmarks.mpc_gate",
)
@pytest.mark.xfail(strict=True, reason="gate not met: 45.7 % within 0.02 on 1,200 problems (H200)")
def test_device_first_action_and_decision_match_osqp_on_every_recorded_problem(data):
    close, same = _gate(data, np.arange(data["x0"].shape[0]))
    print(f"first action within 0.02: {close:.2%}; same decision: {same:.2%}")
    assert close >= 0.99, f"first action within 0.02 on {close:.1%}"
    assert same >= 0.98, f"same decision on {same:.1%}"


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
def test_device_bridge_falls_back_on_nan_and_counts_it(monkeypatch):
    """A NaN in the GP samples never reaches an action: the row falls back (the policy's action,
    here braking) and the reason is counted in the bridge's stats (mpc_reasons)."""
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.mpc import MPCConfig, make_gp_mpc_rollout, make_mpc_bridge
    from mpcpearl_jax.mpc.bridge import MPCBridge

    env = make_env("restaurant")
    tasks = jax.tree_util.tree_map(lambda a: a[:2], make_tasks("restaurant", "test"))
    cfg = MPCConfig(solver="device", sqp_iters=1, num_samples=20, qp_tail_samples=5)
    bridge = make_mpc_bridge(env, cfg.replace(gp_mode="fixed"))
    predict = MPCBridge.predict

    def poisoned(self, key, states, params, rows=None):
        samples, valid = predict(self, key, states, params, rows)
        return samples.at[0].set(jnp.nan), valid

    monkeypatch.setattr(MPCBridge, "predict", poisoned)
    traj = jax.jit(make_gp_mpc_rollout(env, bridge, num_steps=2))(jax.random.PRNGKey(0), tasks)
    assert np.all(np.isfinite(np.asarray(traj["action"])))
    assert np.all(np.asarray(traj["status"])[0] == 3)  # FALLBACK_POLICY: no plan yet
    st = bridge.stats()
    assert st["rows_solved"] == 4 and st["fallbacks"] >= 2
    assert sum(v for k, v in st["reasons"].items() if k != "solved") >= 2
