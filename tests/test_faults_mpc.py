"""Fault injection on the MPC's host side: no solver, bridge or collection state carries from one
iteration or batch of episodes to the next (what makes a resumed run with the MPC exact), and the
MPC worker pool exits when the training process is killed."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from faults_helpers import TIMING, small_cfg

from mpcpearl_jax.training.trainer import Trainer


@pytest.mark.slow  # (~20 s)
def test_mpc_collection_does_not_depend_on_earlier_iterations():
    """eps 0.2: iterations 2-3 rerun from a copy of the state after iteration 1, by the same
    trainer (whose MPC bridge and OSQP solvers have meanwhile solved iterations 2-3), give the
    same state bit for bit: no host-side MPC state (warm-start plans, OSQP's rho) leaks into
    later iterations, which is what makes a resumed run exact."""
    tr = Trainer(small_cfg(0.2))
    state, log = tr.iteration(tr.init_state())
    assert log["mpc_rows"] > 0
    snapshot = jax.tree_util.tree_map(jnp.copy, state)
    runs = []
    for start in (state, snapshot):
        s, logs = start, []
        for _ in range(2):
            s, lg = tr.iteration(s)
            logs.append({k: v for k, v in lg.items() if k not in TIMING})
        runs.append((jax.device_get(s), logs))
    (a, logs_a), (b, logs_b) = runs
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    assert logs_a == logs_b and logs_a[0]["mpc_rows"] > 0
    assert tr.bridge.host.memory(0).episode is not None  # the collector stamps its batches


def test_osqp_solver_state_does_not_carry_between_solves():
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import MPCConfig, RowProblem, SQPSolver, solver_params
    from mpcpearl_jax.mpc.qp_osqp import OSQPSettings

    cfg = MPCConfig()
    p = solver_params(cfg, make_env("restaurant").config, 1)
    rng = np.random.default_rng(0)
    probs = []
    for _ in range(12):
        x0 = np.array([rng.uniform(-4, -1), rng.uniform(-1, 1), rng.uniform(-0.5, 0.5)])
        centre = np.array([rng.uniform(-2, 2), rng.uniform(-1, 1)])
        samples = centre + 0.3 * rng.standard_normal((cfg.horizon, 2, cfg.num_samples, 2))
        box = np.array([[3.0, 3.5]])
        probs.append(
            RowProblem(x0, np.array([4.0, 0.0]), samples, np.ones(2, bool), box, box, np.ones(1))
        )
    qp = OSQPSettings.from_config(cfg)
    reused = SQPSolver(p, qp)
    for prob in probs:
        np.testing.assert_array_equal(reused.solve(prob).u, SQPSolver(p, qp).solve(prob).u)


def test_bridge_forgets_plans_of_an_earlier_episode_batch():
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import MPCConfig, make_mpc_bridge

    env = make_env("restaurant")
    bridge = make_mpc_bridge(env, MPCConfig())
    b, k, s = 2, bridge.cfg.horizon, 1
    z = np.zeros

    def host(stamp):  # a call where no row fires: only the memory bookkeeping runs
        bridge.host(
            b, np.arange(b), z(b, bool), z((b, 3)), np.full(b, 6), z((b, 2)), z((b, s, 2)),
            z((b, s, 2)), z((b, s)), z((b, k, 2, 4, 2)), z((b, 2), bool), np.asarray(stamp),
            np.asarray(0),
        )  # fmt: skip

    memory = bridge.host.memory
    host([1, 10, 20])
    memory(0).plan_t[:] = 5  # plans made at t = 5 in this batch of episodes
    host([1, 10, 20])
    assert memory(0).warm(0, 6) is not None  # same episodes: warm start
    host([1, 10, 21])
    assert memory(0).warm(0, 6) is None  # new episodes: the old plans are gone
    memory(0).plan_t[:] = 5
    host([0, 0, 0])  # no stamp (callers that run one batch): memory kept
    assert memory(0).warm(0, 6) is not None


def _host_call(host, goal_x, t):
    """One host call on 4 fired rows at step t (row 1's goal at x = goal_x), no people, one
    table off the path: (inputs, status)."""
    from mpcpearl_jax.mpc import MPCConfig

    k, n = MPCConfig().horizon, 4
    goal = np.tile([4.0, 0.0], (n, 1))
    goal[1, 0] = goal_x
    pose = np.column_stack([np.linspace(-4, -3, n), np.zeros(n), np.zeros(n)])
    box = np.tile([[3.0, 3.5]], (n, 1, 1))
    return host(
        n, np.arange(n), np.ones(n, bool), pose, np.full(n, t), goal, box, box, np.ones((n, 1)),
        np.zeros((n, k, 2, 100, 2)), np.zeros((n, 2), bool), np.array([1, 7, 7]), np.asarray(0),
    )  # fmt: skip


@pytest.mark.parametrize("fault, goal_x", [("killed", 1000.0), ("hung", -1000.0)])
def test_a_lost_mpc_worker_costs_its_rows_a_fallback_and_the_pool_is_replaced(fault, goal_x):
    """mpc.n_workers > 1: a pool worker killed during a call (SIGKILL), or hung past
    `worker_timeout_s`, makes its row fall back (no plan yet: the policy acts), counted with the
    reason "worker_lost"; the pool is dropped (a hung worker killed) and the next call solves on
    a new one."""
    import multiprocessing
    import os
    import signal
    import time

    from mpc_worker_faults import faulty_solve

    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import FALLBACK_POLICY, SOLVED, HostSolver, MPCConfig

    class FaultyHost(HostSolver):
        worker_solve = staticmethod(faulty_solve)

    timeout = 120.0 if fault == "killed" else 10.0
    cfg = MPCConfig(n_workers=2, worker_timeout_s=timeout)
    host = FaultyHost(make_env("restaurant").config, cfg)
    try:
        _, status = _host_call(host, goal_x, t=0)
        st = host.stats()
        assert status[1] == FALLBACK_POLICY
        assert st["reasons"].get("worker_lost", 0) >= 1 and st["fallbacks"] >= 1
        assert st["status"]["fallback_policy"] == st["reasons"]["worker_lost"]
        assert host._pool is None  # dropped: the next call starts a new one
        deadline = time.time() + 30
        while multiprocessing.active_children() and time.time() < deadline:
            time.sleep(0.1)  # the lost pool's workers end (a hung one is killed)
        assert not multiprocessing.active_children()
        host.reset_stats()
        host.cfg = cfg.replace(worker_timeout_s=120.0)  # the new pool's start-up is not timed
        _, status = _host_call(host, 4.0, t=1)
        assert np.all(status == SOLVED), status
        assert "worker_lost" not in host.stats()["reasons"] and host._pool is not None
        if fault == "killed":  # a worker killed between calls costs no row
            pool = host._pool
            os.kill(next(iter(pool._processes.values())).pid, signal.SIGKILL)
            deadline = time.time() + 30
            while not pool._broken and time.time() < deadline:
                time.sleep(0.05)
            assert pool._broken
            _, status = _host_call(host, 4.0, t=2)
            assert np.all(status == SOLVED) and host._pool is not pool
    finally:
        host.close()


def test_mpc_pool_workers_exit_when_the_training_process_is_killed(tmp_path):
    """A SIGKILLed parent leaves no MPC worker behind (watch_parent)."""
    script = tmp_path / "parent.py"
    script.write_text(
        "import os, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from multiprocessing import get_context\n"
        "from mpcpearl_jax.mpc.pool import watch_parent\n"
        "if __name__ == '__main__':\n"
        "    pool = ProcessPoolExecutor(2, mp_context=get_context('spawn'),\n"
        "                               initializer=watch_parent, initargs=(os.getpid(), 0.2))\n"
        "    pids = set(pool.submit(os.getpid).result() for _ in range(4))\n"
        "    print(' '.join(map(str, pids)), flush=True)\n"
        "    time.sleep(60)\n"
    )
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    pids = [int(p) for p in proc.stdout.readline().split()]
    assert pids
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 10
    alive = pids
    while alive and time.time() < deadline:
        time.sleep(0.2)
        alive = [p for p in pids if _alive(p)]
    assert not alive, f"orphaned MPC workers {alive}"


def _alive(pid: int) -> bool:
    import os

    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped) counts as gone
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except OSError:
        return False
