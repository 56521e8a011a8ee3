"""Risk-aware MPC (paper Sec. III-B, method §6, eq. (4)): GP prediction of the people in JAX
(`gp`); the problem in NumPy (`problem`, with the bicycle model's NumPy twin in `model`); the SQP
on the host (`sqp`) and its QP solver behind one protocol (`qp.QPBackend`; OSQP, `qp_osqp`); the
host side of the bridge's callback (`host`), with its worker pool (`pool`) and each row's previous
plan (`memory`); what the MPC does with one row, its status, fallback and action (`rows`); problems
recorded from training (`recorded`); the bridge that a jitted rollout calls where an
event fires (`bridge`: `init` / `step` / `finish`, one `pure_callback` per step with the fired
rows); the GP-MPC baseline acting at every step (`controller`); the test-time safety shield
(`shield`, an extension); the settings (`config.MPCConfig`)."""

from mpcpearl_jax.mpc.bridge import MPCBridge, make_mpc_bridge
from mpcpearl_jax.mpc.config import MPCConfig
from mpcpearl_jax.mpc.controller import make_gp_mpc_rollout
from mpcpearl_jax.mpc.host import HostSolver
from mpcpearl_jax.mpc.problem import RowProblem, SolveResult, solver_params
from mpcpearl_jax.mpc.qp import QPBackend, QPSettings, QPSolution
from mpcpearl_jax.mpc.qp_osqp import OSQPBackend, OSQPSettings
from mpcpearl_jax.mpc.rows import (
    FALLBACK_PLAN,
    FALLBACK_POLICY,
    NOT_FIRED,
    SOLVED,
    STATUS_NAMES,
)
from mpcpearl_jax.mpc.sqp import SQPSolver

__all__ = [
    "FALLBACK_PLAN",
    "FALLBACK_POLICY",
    "NOT_FIRED",
    "SOLVED",
    "STATUS_NAMES",
    "HostSolver",
    "MPCBridge",
    "MPCConfig",
    "OSQPBackend",
    "OSQPSettings",
    "QPBackend",
    "QPSettings",
    "QPSolution",
    "RowProblem",
    "SQPSolver",
    "SolveResult",
    "make_gp_mpc_rollout",
    "make_mpc_bridge",
    "solver_params",
]
