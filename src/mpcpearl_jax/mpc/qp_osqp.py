"""OSQP as the SQP's QP backend (`mpc.qp.QPBackend`, method §6).

Its settings (`OSQPSettings`) come from the config's `osqp_*` fields (`OSQPSettings.from_config`),
which nothing else reads. Each `update` restarts OSQP's step size rho from the configured value,
so that a QP's solution depends on its own values only, not on the QPs this solver met before
(exact resume; the same row gives the same plan in any pool worker). A Ctrl-C that arrives during
a solve reaches Python and the QP is solved again (`solve_through_stops`).
"""

from __future__ import annotations

import dataclasses
import signal

import numpy as np
import osqp
import scipy.sparse as sp

from mpcpearl_jax.mpc.config import MPCConfig
from mpcpearl_jax.mpc.qp import QPSolution

# An unconverged QP still gives a search direction: the line search on the exact merit decides.
USABLE = (
    osqp.SolverStatus.OSQP_SOLVED,
    osqp.SolverStatus.OSQP_SOLVED_INACCURATE,
    osqp.SolverStatus.OSQP_MAX_ITER_REACHED,
)


@dataclasses.dataclass(frozen=True)
class OSQPSettings:
    """OSQP's settings (its own names); `from_config` reads them from `MPCConfig.osqp_*`."""

    eps_abs: float
    eps_rel: float
    max_iter: int
    rho: float
    check_termination: int
    adaptive_rho_interval: int
    polishing: bool

    @classmethod
    def from_config(cls, cfg: MPCConfig) -> OSQPSettings:
        return cls(
            eps_abs=cfg.osqp_eps_abs,
            eps_rel=cfg.osqp_eps_rel,
            max_iter=cfg.osqp_max_iter,
            rho=cfg.osqp_rho,
            check_termination=cfg.osqp_check_termination,
            adaptive_rho_interval=cfg.osqp_adaptive_rho_interval,
            polishing=cfg.osqp_polish,
        )

    def backend(self) -> OSQPBackend:
        return OSQPBackend(self)


def solve_through_stops(solver: osqp.OSQP, x0: np.ndarray, y0: np.ndarray, rho: float):
    """`solver.solve()` from the warm start (x0, y0), its result the same whether or not a Ctrl-C
    (SIGINT) arrives during it. OSQP takes SIGINT with a handler of its own while it solves: it
    prints "Solver interrupted", returns status OSQP_SIGINT, and Python never sees the signal.
    Here the signal goes on to Python's handler (a command's stop: the training saves and stops;
    KeyboardInterrupt; ignored in the MPC's pool workers) and the QP is solved again from the
    same start and step size rho."""
    while True:
        solver.warm_start(x=x0, y=y0)
        res = solver.solve(raise_error=False)
        if res.info.status_val != osqp.SolverStatus.OSQP_SIGINT:
            return res
        signal.raise_signal(signal.SIGINT)  # Python's handler runs now (it may raise)
        solver.update_settings(rho=rho)


class OSQPBackend:
    """One OSQP solver for QPs of one sparsity pattern (`mpc.qp.QPBackend`)."""

    def __init__(self, settings: OSQPSettings):
        self.settings = settings
        self._solver: osqp.OSQP | None = None

    def setup(
        self, P: sp.csc_matrix, q: np.ndarray, A: sp.csc_matrix, lo: np.ndarray, hi: np.ndarray
    ) -> None:
        self._solver = osqp.OSQP()
        self._solver.setup(
            P, q, A, lo, hi, **dataclasses.asdict(self.settings), warm_starting=True, verbose=False
        )

    def update(self, q: np.ndarray, a_data: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        if self._solver is None:
            raise RuntimeError("OSQPBackend.update before setup")
        # OSQP keeps the step size rho its adaptive scheme reached in the previous solve: restart
        # every QP from the configured rho, so that a solve depends on its own inputs only
        self._solver.update_settings(rho=self.settings.rho)
        self._solver.update(q=q, l=lo, u=hi, Ax=a_data)

    def solve(self, x0: np.ndarray, y0: np.ndarray) -> QPSolution:
        if self._solver is None:
            raise RuntimeError("OSQPBackend.solve before setup")
        res = solve_through_stops(self._solver, x0, y0, self.settings.rho)
        status = res.info.status_val
        return QPSolution(res.x, status in USABLE, str(res.info.status), int(res.info.iter))
