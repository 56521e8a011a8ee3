"""The MPC's host pool and the bridge's operands (`mpc.host`, `mpc.bridge`): the pool's size per
machine, rows solved in the pool equal to rows solved in the calling process, the pool started
ahead of the first call, and the packed callback operands equal to the arrays they pack."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.mpc import HostSolver, MPCConfig
from mpcpearl_jax.mpc.bridge import pack_rows
from mpcpearl_jax.mpc.host import unpack_rows
from mpcpearl_jax.mpc.pool import MAX_AUTO_WORKERS, pool_size

PROBLEMS = Path(__file__).parent / "data" / "mpc_problems.npz"


def test_pool_size_is_at_most_one_worker_per_core():
    assert pool_size(1, cores=16) == 1  # no pool: the calling process solves
    assert pool_size(2, cores=16) == 2
    assert pool_size(8, cores=2) == 2  # never more workers than cores
    assert pool_size(3, cores=1) == 1
    assert pool_size(0, cores=2) == 2  # 0: one per core
    assert pool_size(0, cores=64) == MAX_AUTO_WORKERS
    assert MPCConfig(n_workers=0).n_workers == 0
    with pytest.raises(ConfigError, match="n_workers"):
        MPCConfig(n_workers=-1)


def test_packed_operands_unpack_to_the_same_values_and_dtypes():
    rng = np.random.default_rng(0)
    arrays = (
        jnp.arange(5, dtype=jnp.int32),
        jnp.asarray([True, False, True, True, False]),
        jnp.asarray(rng.normal(size=(5, 3)), jnp.float32),
        jnp.asarray(rng.normal(size=(5, 10, 2, 7, 2)), jnp.float32),
        jnp.asarray(rng.random((5, 2)) < 0.5),
        jnp.asarray(rng.normal(size=(5, 4)), jnp.float32),
    )
    floats, ints, layout = pack_rows(arrays)
    assert floats.shape == (5, 3 + 10 * 2 * 7 * 2 + 4) and ints.shape == (5, 1 + 1 + 2)
    back = unpack_rows(layout, np.asarray(floats), np.asarray(ints))
    for a, b in zip(arrays, back, strict=True):
        assert b.dtype == np.asarray(a).dtype
        np.testing.assert_array_equal(b, np.asarray(a))


def _call(host, rows, data, probs):
    """One host call on recorded problems `rows`, all fired, at step 30, no people masked."""
    n = len(rows)
    return host(
        n, np.arange(n, dtype=np.int32), np.ones(n, bool), probs.x0[rows], np.full(n, 30, np.int32),
        probs.goal[rows], probs.static_lo[rows], probs.static_hi[rows], probs.static_radius[rows],
        probs.samples[rows], probs.valid[rows], np.zeros(3, np.uint32), np.asarray(0),
    )  # fmt: skip


def test_rows_solved_in_the_pool_equal_rows_solved_here():
    """A call's outputs do not depend on where its rows are solved (each row's result depends
    only on its problem and start); the pool started ahead (`start`) serves the first call, and
    a call in the pool records its send and return times; one row is solved here."""
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import recorded

    rec = recorded.load(PROBLEMS)
    data, probs = rec.data, rec.batch
    nav = make_env("restaurant").config
    cfg = MPCConfig(sqp_iters=2, sqp_step_tol=0.05, line_search_steps=3, unsafe_recovery=True)
    rows = np.array([3, 150, 420, 700, 1010])
    here = HostSolver(nav, cfg)
    want = _call(here, rows, data, probs)
    pool = HostSolver(nav, cfg.replace(n_workers=2))
    try:
        pool.start()
        if pool.n_workers > 1:
            assert pool._pool is not None
        got = _call(pool, rows, data, probs)
        for a, b in zip(want, got, strict=True):
            np.testing.assert_array_equal(a, b)
        st = pool.stats()
        if pool.n_workers > 1:
            assert len(st["pool_send_s"]) == len(st["pool_return_s"]) == 1
            pool.reset_stats()
            one = _call(pool, rows[:1], data, probs)  # one row: solved in this process
            np.testing.assert_array_equal(one[0], want[0][:1])
            assert pool.stats()["pool_send_s"] == []
    finally:
        pool.close()
