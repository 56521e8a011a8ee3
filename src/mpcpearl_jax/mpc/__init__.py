"""Risk-aware MPC (paper Sec. III-B, method §6): GP prediction in JAX, SQP on OSQP, host bridge."""

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
