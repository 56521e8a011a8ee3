"""Risk-aware MPC (paper Sec. III-B, method §6, eq. (4)): GP prediction of the people in JAX
(`gp`); the SQP on the host, on OSQP (`solver`, with the bicycle model's NumPy twin in `model`),
or on the device (`device_solver`, `device_bridge`: `mpc.solver = "device"`); the bridge that a
jitted rollout calls where an event fires (`bridge`: one `pure_callback` per step to the host
solver, or the device path); the GP-MPC baseline acting at every step (`controller`); the
test-time safety shield (`shield`, an extension); the settings (`config.MPCConfig`)."""

from mpcpearl_jax.mpc.bridge import (
    FALLBACK_PLAN,
    FALLBACK_POLICY,
    NOT_FIRED,
    SOLVED,
    STATUS_NAMES,
    MPCBridge,
    make_mpc_bridge,
)
from mpcpearl_jax.mpc.config import MPCConfig
from mpcpearl_jax.mpc.controller import make_gp_mpc_rollout
from mpcpearl_jax.mpc.solver import RowProblem, SolveResult, SQPSolver, solver_params

__all__ = [
    "FALLBACK_PLAN",
    "FALLBACK_POLICY",
    "NOT_FIRED",
    "SOLVED",
    "STATUS_NAMES",
    "MPCBridge",
    "MPCConfig",
    "RowProblem",
    "SQPSolver",
    "SolveResult",
    "make_gp_mpc_rollout",
    "make_mpc_bridge",
    "solver_params",
]
