"""A pool worker's solve with faults, for tests/test_faults_mpc.py (a module of its own, so that
the spawned workers import only this and the solver): a row whose goal's x is above 100 kills
its worker (SIGKILL), one below -100 hangs it."""

from __future__ import annotations

import os
import signal
import time

from mpcpearl_jax.mpc.host import solve_in_worker


def faulty_solve(params, prob, u_init, qp=None):
    if prob.goal[0] > 100:
        os.kill(os.getpid(), signal.SIGKILL)
    if prob.goal[0] < -100:
        time.sleep(600)
    return solve_in_worker(params, prob, u_init, qp)
