"""The SQP's seam to its QP solver (method §6): one protocol, `QPBackend`, for any solver of the
convex QP of one SQP iteration (`mpc.sqp`),

    minimize 1/2 z'Pz + q'z  subject to  lo <= A z <= hi,

in a sequence of QPs of one sparsity pattern: `setup` once with the pattern (P and A as CSC
matrices) and the first QP's values, `update` with each next QP's values (q, A's nonzeros in the
order of `setup`'s CSC matrix, lo, hi; P is fixed), `solve` from a warm start (primal z0, dual
y0), which reports the solution, whether it gives a search direction, the solver's status and
iterations (`QPSolution`).

A backend is made by its settings (`QPSettings`): a frozen, picklable dataclass whose `backend()`
returns a fresh solver, so that the settings travel to the pool's workers and key their cached
solvers. OSQP is the one backend (`mpc.qp_osqp`, its settings read from the config's `osqp_*`
fields).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import scipy.sparse as sp


class QPSolution(NamedTuple):
    """x: the primal solution [n] (None where the solver gives none); usable: whether x is a search
    direction for the SQP (solved, or stopped early at the iteration cap or inaccurate: the line
    search on the exact merit decides); status: the solver's own word; iters: its iterations."""

    x: np.ndarray | None
    usable: bool
    status: str
    iters: int


class QPBackend(Protocol):
    """A QP solver for a sequence of QPs of one sparsity pattern (see the module)."""

    def setup(
        self, P: sp.csc_matrix, q: np.ndarray, A: sp.csc_matrix, lo: np.ndarray, hi: np.ndarray
    ) -> None: ...

    def update(self, q: np.ndarray, a_data: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        """The next QP's values; its result must not depend on the QPs solved before."""
        ...

    def solve(self, x0: np.ndarray, y0: np.ndarray) -> QPSolution: ...


class QPSettings(Protocol):
    """A backend's settings: hashable and picklable (a frozen dataclass of plain values)."""

    def backend(self) -> QPBackend: ...
