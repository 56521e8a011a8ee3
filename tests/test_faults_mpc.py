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
    assert tr.bridge._episode is not None  # the collector stamps its batches of episodes


def test_osqp_solver_state_does_not_carry_between_solves():
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import MPCConfig, RowProblem, SQPSolver, solver_params

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
    reused = SQPSolver(p)
    for prob in probs:
        np.testing.assert_array_equal(reused.solve(prob).u, SQPSolver(p).solve(prob).u)


def test_bridge_forgets_plans_of_an_earlier_episode_batch():
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import MPCConfig, make_mpc_bridge

    env = make_env("restaurant")
    bridge = make_mpc_bridge(env, MPCConfig())
    b, k, s = 2, bridge.cfg.horizon, 1
    z = np.zeros

    def host(stamp):  # a call where no row fires: only the memory bookkeeping runs
        bridge._host(
            z(b, bool), z((b, 3)), np.full(b, 6), z((b, 2)), z((b, s, 2)), z((b, s, 2)),
            z((b, s)), z((b, k, 2, 4, 2)), z((b, 2), bool), np.asarray(stamp), np.asarray(0),
        )  # fmt: skip

    host([1, 10, 20])
    bridge._plan_t[:] = 5  # plans made at t = 5 in this batch of episodes
    host([1, 10, 20])
    assert bridge._warm_plan(0, 6) is not None  # same episodes: warm start
    host([1, 10, 21])
    assert bridge._warm_plan(0, 6) is None  # new episodes: the old plans are gone
    bridge._plan_t[:] = 5
    host([0, 0, 0])  # no stamp (callers that run one batch): memory kept
    assert bridge._warm_plan(0, 6) is not None


def test_mpc_pool_workers_exit_when_the_training_process_is_killed(tmp_path):
    """A SIGKILLed parent leaves no MPC worker behind (watch_parent)."""
    script = tmp_path / "parent.py"
    script.write_text(
        "import os, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from multiprocessing import get_context\n"
        "from mpcpearl_jax.mpc.solver import watch_parent\n"
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
