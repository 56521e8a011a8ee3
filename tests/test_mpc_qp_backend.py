"""The SQP's seam to its QP solver (`mpc.qp.QPBackend`): a second backend plugs in through the
protocol alone and gives the same plans, the QP settings reach the pool's workers, and only the
OSQP backend reads the config's `osqp_*` fields."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mpcpearl_jax.envs import make_env
from mpcpearl_jax.mpc import HostSolver, MPCConfig, OSQPSettings, SQPSolver
from mpcpearl_jax.mpc.pool import pool_size
from mpcpearl_jax.mpc.problem import SolverParams, solver_params
from mpcpearl_jax.mpc.recorded import load

ROOT = Path(__file__).resolve().parents[1]
PROBLEMS = ROOT / "tests" / "data" / "mpc_problems.npz"
ROWS = (3, 150, 420, 700, 1010)
CALLS: dict[str, int] = {"setup": 0, "update": 0, "solve": 0}


class _Counting:
    """A QP backend of its own: counts the calls the SQP makes and passes them on to OSQP."""

    def __init__(self, inner):
        self.inner = inner

    def setup(self, P, q, A, lo, hi):
        CALLS["setup"] += 1
        assert P.format == A.format == "csc" and A.shape == (lo.size, q.size)
        assert hi.size == lo.size and P.shape == (q.size, q.size)
        self.nnz = A.nnz
        self.inner.setup(P, q, A, lo, hi)

    def update(self, q, a_data, lo, hi):
        CALLS["update"] += 1
        assert a_data.shape == (self.nnz,)  # the pattern set up once
        self.inner.update(q, a_data, lo, hi)

    def solve(self, x0, y0):
        CALLS["solve"] += 1
        return self.inner.solve(x0, y0)


@dataclasses.dataclass(frozen=True)
class CountingQP:
    inner: OSQPSettings

    def backend(self) -> _Counting:
        return _Counting(self.inner.backend())


@pytest.fixture(scope="module")
def rec():
    return load(PROBLEMS)


def _call(host, rec, rows):
    """One host call on recorded problems `rows`, all fired, at step 30."""
    b, n = rec.batch, len(rows)
    rows = np.asarray(rows)
    return host(
        n, np.arange(n, dtype=np.int32), np.ones(n, bool), b.x0[rows], np.full(n, 30, np.int32),
        b.goal[rows], b.static_lo[rows], b.static_hi[rows], b.static_radius[rows],
        b.samples[rows], b.valid[rows], np.zeros(3, np.uint32), np.asarray(0),
    )  # fmt: skip


def test_a_second_backend_plugs_in_through_the_protocol_and_gives_the_same_plans(rec):
    """A backend that only wraps OSQP's, passed as the host's QP settings: the host's outputs and
    every row's SQP result are those of the default backend, and the SQP set its pattern up once
    and updated values for every later QP."""
    nav = make_env("restaurant").config
    cfg = MPCConfig(sqp_iters=3, sqp_step_tol=1e-3, unsafe_recovery=True)
    want = _call(HostSolver(nav, cfg), rec, ROWS)
    CALLS.update(setup=0, update=0, solve=0)
    host = HostSolver(nav, cfg, qp=CountingQP(OSQPSettings.from_config(cfg)))
    got = _call(host, rec, ROWS)
    for a, b in zip(want, got, strict=True):
        np.testing.assert_array_equal(a, b)
    n_qp = sum(host.stats()["n_qp"])
    assert CALLS == {"setup": 1, "update": n_qp - 1, "solve": n_qp} and n_qp >= len(ROWS)
    params = dataclasses.replace(rec.params, sqp_iters=3, multi_start="always")
    counted = SQPSolver(params, CountingQP(rec.qp))
    plain = SQPSolver(params, rec.qp)
    for i in ROWS:
        a, b = plain.solve(*rec.row(i)), counted.solve(*rec.row(i))
        np.testing.assert_array_equal(a.u, b.u)
        assert (a.reason, a.merit, a.n_qp, a.qp_iters) == (b.reason, b.merit, b.n_qp, b.qp_iters)


def test_the_qp_settings_decide_the_plans_and_reach_the_pool_workers(rec):
    """OSQP capped at 3 iterations per QP changes some plans; the pool's workers solve with the
    host's settings (the rows equal those solved here with the same settings)."""
    nav = make_env("restaurant").config
    cfg = MPCConfig(sqp_iters=3, sqp_step_tol=1e-3)
    capped = OSQPSettings.from_config(cfg.replace(osqp_max_iter=3))
    assert capped == dataclasses.replace(OSQPSettings.from_config(cfg), max_iter=3)
    default = _call(HostSolver(nav, cfg), rec, ROWS)
    here = _call(HostSolver(nav, cfg, qp=capped), rec, ROWS)
    assert not np.array_equal(default[0], here[0])
    if pool_size(2) < 2:
        pytest.skip("one core: no pool")
    pool = HostSolver(nav, cfg.replace(n_workers=2), qp=capped)
    try:
        got = _call(pool, rec, ROWS)
        assert pool.stats()["pool_send_s"]  # solved in the pool
    finally:
        pool.close()
    for a, b in zip(here, got, strict=True):
        np.testing.assert_array_equal(a, b)


def test_only_the_osqp_backend_reads_the_configs_osqp_fields():
    """The solver-neutral problem carries no solver settings, and no module but `mpc.qp_osqp`
    reads an `osqp_*` field of the config."""
    assert not [f.name for f in dataclasses.fields(SolverParams) if "osqp" in f.name]
    nav = make_env("restaurant").config
    a = solver_params(MPCConfig(), nav, 2)
    assert a == solver_params(MPCConfig(osqp_rho=0.3, osqp_max_iter=7, osqp_polish=True), nav, 2)
    readers = []
    for path in sorted((ROOT / "src" / "mpcpearl_jax").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr.startswith("osqp_"):
                readers.append(str(path.relative_to(ROOT)))
    assert set(readers) == {"src/mpcpearl_jax/mpc/qp_osqp.py"}, readers
