"""Training results do not depend on the MPC's worker processes (`mpc.n_workers`).

The same short run (the `default` preset at test sizes, eps 0.2, the real SQP on OSQP: no
stand-in) with its fired rows solved in the calling process (1 worker) and in pools of 2 and 4
worker processes gives the same metrics and the same trained parameters, bit for bit (wall
times aside). A pool hands each row to whichever worker is free, so which worker solves a row,
and what that worker solved before, changes from call to call: this holds because each row's
warm start (its previous plan, `PlanMemory`) lives with the row in the calling
process and travels with the row, and a solver keeps nothing from one row to the next (OSQP's
step size is restarted for every QP). It is what lets the presets take one worker per core
(`n_workers=0`) and a committed run, trained with 2, be rebuilt and resumed with any count
(`config.RESULT_NEUTRAL`).

The fast tests check the host side alone, in seconds: the rows of three successive calls (warm
starts included) solved the same in the calling process and in pools of 2 and 4, and a solver
that solved other rows before giving the same result as a new one. The slow tests train: one
trainer three times (1 worker, then pools of 2 and 4), switching only its host solver's worker
count, so the programs compile once (about a minute on a 2-core CPU; the rollouts, which call
the host, are not kept by the compilation cache); and a trainer per count built from the
config, as a command does.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pytest

from mpcpearl_jax.mpc.host import HostSolver
from tests.test_fingerprint import tiny

ITERATIONS = 2
PROBLEMS = Path(__file__).parent / "data" / "mpc_problems.npz"
EXPERT = dict(sqp_iters=2, sqp_step_tol=0.05, line_search_steps=3, unsafe_recovery=True)


def _host_run(workers: int) -> tuple[list, dict]:
    """Three calls of one host solver on a batch of 8 rows at steps 30, 31, 32 (one batch of
    episodes), each row a recorded problem: every row fires in the first two calls, five in
    the third; the rows hold their plans between calls, so the later calls warm-start. Per call
    its outputs and the plan memory after it; the SQP's starts."""
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import MPCConfig, recorded

    rec = recorded.load(PROBLEMS)
    batch = 8
    host = HostSolver(make_env("restaurant").config, MPCConfig(n_workers=workers, **EXPERT))
    rng = np.random.default_rng(0)
    out = []
    try:
        for t, n in ((30, batch), (31, batch), (32, 5)):
            rows = np.sort(rng.choice(batch, n, replace=False)).astype(np.int32)
            pick = rng.choice(len(rec), n, replace=False)
            p = rec.batch
            inputs, status = host(
                batch, rows, np.ones(n, bool), p.x0[pick], np.full(n, t, np.int32), p.goal[pick],
                p.static_lo[pick], p.static_hi[pick], p.static_radius[pick], p.samples[pick],
                p.valid[pick], np.array([1, 7, 0], np.uint32), np.asarray(0),
            )  # fmt: skip
            mem = host.memory(0)
            out.append((inputs, status, mem.plans.copy(), mem.plan_t.copy()))
        return out, host.stats()["starts"]
    finally:
        host.close()


def test_each_row_solves_the_same_with_1_2_and_4_workers(pools):
    """The host side alone, in seconds: the calls' actions, statuses and the rows' plans are the
    same whichever worker solves a row and whatever it solved before; the warm starts come from
    each row's own previous plan (kept in the calling process), not from a worker."""
    ref, starts = _host_run(1)
    assert starts.get("warm", 0) >= 5  # the later calls warm-started
    assert pools == []
    for workers in (2, 4):
        pools.clear()
        got, got_starts = _host_run(workers)
        assert len(pools) == 3 and max(pools) == 8  # every call's rows in the pool
        assert got_starts == starts
        for k, (a, b) in enumerate(zip(ref, got, strict=True)):
            for x, y in zip(a, b, strict=True):
                assert np.array_equal(x, y), f"{workers} workers, call {k + 1}"


def test_a_solver_keeps_nothing_from_one_row_to_the_next():
    """A pool worker's solver solves the rows it is handed one after the other: each row's
    result is the same as a new solver's on that row alone."""
    from mpcpearl_jax.mpc import SQPSolver, recorded

    rec = recorded.load(PROBLEMS)
    params = dataclasses.replace(rec.params, **EXPERT)
    one = SQPSolver(params, rec.qp)
    for i in range(0, len(rec), 97):
        row, init = rec.row(i)
        a, b = one.solve(row, init), SQPSolver(params, rec.qp).solve(row, init)
        assert np.array_equal(a.u, b.u) and a.reason == b.reason, i
        assert np.array_equal(a.merit, b.merit, equal_nan=True), i
        assert (a.qp_iters, a.n_qp, a.stop, a.start) == (b.qp_iters, b.n_qp, b.stop, b.start)


def _cfg(workers: int):
    cfg = tiny("default")
    # four tasks a visit: calls with several fired rows, for the pool to share out
    train = dataclasses.replace(cfg.train, iterations=ITERATIONS, tasks_per_iteration=4)
    return cfg.replace(train=train, mpc=cfg.mpc.replace(n_workers=workers))


@pytest.fixture
def pools(monkeypatch):
    """The pool sizes as configured (not capped at this machine's cores: a pool of 4 on 2 cores
    solves the same rows, only slower), and the rows each call solved in a pool."""
    monkeypatch.setattr(HostSolver, "n_workers", property(lambda self: self.cfg.n_workers))
    pooled: list[int] = []
    original = HostSolver._solve_in_pool

    def counting(self, params, probs, inits):
        pooled.append(len(probs))
        return original(self, params, probs, inits)

    monkeypatch.setattr(HostSolver, "_solve_in_pool", counting)
    return pooled


def _train(tr, workers: int) -> tuple[list[dict], list[np.ndarray]]:
    """Two iterations from a new state; (per iteration the logged numbers, the parameters)."""
    state = tr.init_state()
    logs = []
    for _ in range(ITERATIONS):
        state, log = tr.iteration(state)
        logs.append({k: np.asarray(v) for k, v in log.items() if not k.endswith("_s")})
    assert logs[0]["mpc_rows"] > 0, "the MPC acted on no row"
    return logs, [np.asarray(x) for x in jax.tree_util.tree_leaves(state.learner.params)]


def _same(ref, got, workers: int) -> None:
    for i, (a, b) in enumerate(zip(ref[0], got[0], strict=True)):
        assert sorted(a) == sorted(b)
        for k in a:
            assert np.array_equal(a[k], b[k]), f"{workers} workers, iteration {i + 1}: {k}"
    for a, b in zip(ref[1], got[1], strict=True):
        assert np.array_equal(a, b), f"{workers} workers: the parameters differ"


@pytest.mark.slow
def test_one_trainer_gives_the_same_run_with_1_2_and_4_workers(pools):
    from mpcpearl_jax.training.trainer import Trainer

    tr = Trainer(_cfg(1))
    host = tr.bridge.host
    try:
        ref = _train(tr, 1)
        assert pools == []  # one worker: every row solved here
        for workers in (2, 4):
            host.close()
            host.cfg = host.cfg.replace(n_workers=workers)
            pools.clear()
            got = _train(tr, workers)
            assert pools and max(pools) >= 2, f"{workers} workers: no call used the pool"
            _same(ref, got, workers)
    finally:
        tr.close()


@pytest.mark.slow
def test_a_trainer_per_worker_count_gives_the_same_run(pools):
    from mpcpearl_jax.training.trainer import Trainer

    runs = {}
    for workers in (1, 2, 4):
        pools.clear()
        tr = Trainer(_cfg(workers))
        try:
            runs[workers] = _train(tr, workers)
        finally:
            tr.close()
        assert bool(pools) == (workers > 1)
    for workers in (2, 4):
        _same(runs[1], runs[workers], workers)
