"""The MPC's SQP (method §6, paper eq. (4)) on the host: `SQPSolver` solves one row's problem
(`mpc.problem`) through a QP backend (`mpc.qp.QPBackend`; OSQP by default, `mpc.qp_osqp`).

The QP's sparsity pattern is built once per problem size and set up once in the backend; each
QP only updates values (the backend's result depends on its own values only, not on the QPs
before). Each SQP iteration warm-starts the QP from the plan itself (the shifted previous plan
at first), bounds the inputs by a trust region and accepts steps by a line search on the exact
SAA merit (cost + slack_penalty * violations).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from mpcpearl_jax.mpc import model
from mpcpearl_jax.mpc.problem import (
    Linearization,
    QPLayout,
    RowProblem,
    SolveResult,
    SolverParams,
    SQPRun,
    clip_inputs,
    linearize_problem,
    merit,
    qp_bounds,
    qp_pattern,
    qp_values,
    stage_weights,
    starts,
    violations,
)
from mpcpearl_jax.mpc.qp import QPBackend, QPSettings


class SQPSolver:
    """The SQP for problems of one size (K, M, N_adapt, S), with a fixed sparsity pattern; its QPs
    by the backend of `qp`, the run's (e.g. `qp_osqp.OSQPSettings.from_config(cfg.mpc)`): no
    default, so that no solver runs on other QP settings than its run's."""

    def __init__(self, params: SolverParams, qp: QPSettings):
        self.p = params
        self.qp = qp
        self.lay = QPLayout(params)
        self._cost_scale = 1.0 / params.slack_penalty  # QP objective in units of the penalty
        rows, cols = qp_pattern(params, self.lay)
        order = sp.csc_matrix(
            (np.arange(1, rows.size + 1, dtype=float), (rows, cols)), shape=(self.lay.m, self.lay.n)
        )
        if order.nnz != rows.size:
            raise AssertionError("duplicate entries in the QP pattern")
        self._perm = order.data.astype(np.int64) - 1  # CSC slot -> triplet index
        self._indices, self._indptr = order.indices.copy(), order.indptr.copy()
        self._P = self._cost_matrix()
        self._backend: QPBackend | None = None

    def _cost_matrix(self) -> sp.csc_matrix:
        p, lay = self.p, self.lay
        diag = np.zeros(lay.n)
        diag[lay.u : lay.x] = 2.0 * p.r_weight
        w = stage_weights(p)
        diag[lay.x + 3 * np.arange(p.horizon)] = 2.0 * w
        diag[lay.x + 3 * np.arange(p.horizon) + 1] = 2.0 * w
        diag[lay.xi : lay.s] = 1e-3  # keeps xi bounded when no person constrains
        return sp.diags(diag * self._cost_scale).tocsc()

    def _linear_cost(self, goal: np.ndarray) -> np.ndarray:
        p, lay = self.p, self.lay
        q = np.zeros(lay.n)
        w = stage_weights(p)
        for j in range(2):
            q[lay.x + 3 * np.arange(p.horizon) + j] = -2.0 * w * goal[j]
        q[lay.es :] = p.slack_penalty
        return q * self._cost_scale

    def _matrix(self, data: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(self.lay.m, self.lay.n))

    def _primal_guess(self, lin: Linearization, u: np.ndarray, xs: np.ndarray) -> np.ndarray:
        """Primal start: the plan itself plus consistent xi, s and slacks."""
        p, lay = self.p, self.lay
        z = np.zeros(lay.n)
        z[lay.u : lay.x] = u.ravel()
        z[lay.x : lay.xi] = xs[1:].ravel()
        pos = xs[1:, :2]
        loss = lin.samp_lo - np.einsum("ktj,kj->kt", lin.samp_grad, pos)  # [K, T], sorted desc.
        tail = min(int(np.ceil(p.num_samples * (1.0 - p.alpha))), p.qp_samples)
        xi = np.where(np.isfinite(loss[:, tail - 1]), loss[:, tail - 1], 0.0)  # the VaR
        z[lay.xi : lay.s] = xi
        z[lay.s : lay.es] = np.maximum(np.nan_to_num(loss - xi[:, None], neginf=0.0), 0.0).ravel()
        stat = lin.stat_lo - np.einsum("ksj,kj->ks", lin.stat_grad, pos)
        z[lay.es : lay.ec] = np.maximum(stat, 0.0).ravel()
        return z

    def _solve_qp(self, prob: RowProblem, u: np.ndarray, xs: np.ndarray):
        """One QP at the plan; returns (u_qp [K, 2] or None, the backend's iterations)."""
        lin = linearize_problem(self.p, prob, u, xs)
        a_data = qp_values(self.p, lin)[self._perm]  # A's nonzeros in CSC order
        lo, hi = qp_bounds(self.p, self.lay, lin, u)
        q = self._linear_cost(prob.goal)
        if self._backend is None:
            self._backend = self.qp.backend()
            self._backend.setup(self._P, q, self._matrix(a_data), lo, hi)
        else:
            self._backend.update(q, a_data, lo, hi)
        guess = self._primal_guess(lin, u, xs)
        sol = self._backend.solve(guess, np.zeros(self.lay.m))
        if not sol.usable or sol.x is None or not np.all(np.isfinite(sol.x[: self.lay.xi])):
            return None, sol.iters
        return sol.x[self.lay.u : self.lay.x].reshape(-1, 2), sol.iters

    def solve(self, prob: RowProblem, u_init: np.ndarray | None = None) -> SolveResult:
        """SQP from the plan u_init [K, 2] (cold start if None); never raises on solver failure.

        With `multi_start` "always" the SQP also runs from the other starts of `starts` (cold,
        standing still) and the safe plan of lowest exact merit is kept; with "on_failure" the
        other starts run only when the first plan is not safe. Where no start gives a safe plan,
        the first start's result stands (and the caller falls back as without multi-start).

        With `unsafe_recovery` (extension), a plan whose first stage is unsafe is solved once more
        from the least-violating first move of a 3 x 3 input grid, and a plan whose first move is
        itself the least violating one available is used (reason "least_violation").
        """
        t0 = time.perf_counter()
        p = self.p
        plan = starts(p, prob, u_init)
        name, u0 = plan[0]
        run = self._sqp(prob, clip_inputs(p, u0))
        iters, n_qp = run.qp_iters, run.n_qp
        if p.multi_start == "always" or (p.multi_start == "on_failure" and run.reason != "solved"):
            best = (run, name) if run.reason == "solved" else None
            for other, u_other in plan[1:]:
                alt = self._sqp(prob, clip_inputs(p, u_other))
                iters, n_qp = iters + alt.qp_iters, n_qp + alt.n_qp
                if alt.reason == "solved" and (best is None or alt.merit < best[0].merit):
                    best = (alt, other)
            if best is not None:
                run, name = best
        u, xs, cur, reason, stop = run.u, run.xs, run.merit, run.reason, run.stop
        if reason == "unsafe" and p.unsafe_recovery:
            least, least_u = self._grid_first_moves(prob, u)
            again = self._sqp(prob, least_u)
            iters, n_qp = iters + again.qp_iters, n_qp + again.n_qp
            if again.reason == "solved":
                u, xs, cur, reason, stop = again.u, again.xs, again.merit, again.reason, again.stop
            else:
                for cand in ((u, xs, cur), (again.u, again.xs, again.merit)):
                    if np.all(np.isfinite(cand[0])) and self._first_violation(prob, cand[1]) <= (
                        least + p.unsafe_tol
                    ):
                        u, xs, cur = cand
                        reason = "least_violation"
                        break
        ok = reason in ("solved", "least_violation")
        elapsed = time.perf_counter() - t0
        return SolveResult(u, xs, ok, reason, iters, n_qp, elapsed, cur, stop, name)

    def _sqp(self, prob: RowProblem, u: np.ndarray) -> SQPRun:
        """SQP iterations from u, at most `sqp_iters` QPs. Every accepted step lowers the exact
        merit, so the plan returned is the best iterate whatever ends the loop (`stop` says
        what did)."""
        p = self.p
        xs = model.rollout(prob.x0, u, p.dt, p.wheelbase)
        cur = merit(p, prob, u, xs)
        iters, n_qp, reason, stop = 0, 0, "solved", "capped"
        for _ in range(p.sqp_iters):
            u_qp, it = self._solve_qp(prob, u, xs)
            iters, n_qp = iters + it, n_qp + 1
            if u_qp is None:
                reason = "qp_failed" if n_qp == 1 else reason
                stop = "qp_failed"
                break
            step = self._line_search(prob, u, clip_inputs(p, u_qp) - u, cur)
            if step is None:
                stop = "stalled"
                break
            u, xs, cur, size = step
            if size < p.sqp_step_tol:
                stop = "converged"
                break
        if reason == "solved" and not np.all(np.isfinite(u)):
            reason = "nonfinite"
        if reason == "solved" and not self.first_stage_safe(prob, xs):
            reason = "unsafe"
        return SQPRun(u, xs, cur, iters, n_qp, reason, stop)

    def _first_violation(self, prob: RowProblem, xs: np.ndarray) -> float:
        """The larger first-stage violation of eq. (4c) and eq. (4b) (>= 0)."""
        static, cvar = violations(self.p, prob, xs)
        return float(max(static[0].max(initial=0.0), cvar[0]))

    def _grid_first_moves(self, prob: RowProblem, u: np.ndarray) -> tuple[float, np.ndarray]:
        """The least first-stage violation over first inputs (0, v_max / 2, v_max) x (-max, 0,
        +max steering) with the rest of plan u, and that plan."""
        p = self.p
        best, best_u = np.inf, u
        for v in (0.0, 0.5 * p.v_max, p.v_max):
            for d in (-p.steer_max, 0.0, p.steer_max):
                u_c = u.copy()
                u_c[0] = (v, d)
                viol = self._first_violation(prob, model.rollout(prob.x0, u_c, p.dt, p.wheelbase))
                if viol < best:
                    best, best_u = viol, u_c
        return best, best_u

    def _line_search(self, prob: RowProblem, u: np.ndarray, du: np.ndarray, cur: float):
        """Backtracking on the exact SAA merit; (u, xs, merit, |step|_inf) or None."""
        p = self.p
        t = 1.0
        for _ in range(max(p.line_search_steps, 1)):
            u_t = u + t * du
            xs_t = model.rollout(prob.x0, u_t, p.dt, p.wheelbase)
            m_t = merit(p, prob, u_t, xs_t)
            if m_t < cur:
                return u_t, xs_t, m_t, float(np.max(np.abs(t * du)))
            t *= 0.5
        return None

    def first_stage_safe(self, prob: RowProblem, xs: np.ndarray) -> bool:
        """The executed stage x_{t+1|t} meets eq. (4c) and eq. (4b) up to unsafe_tol."""
        return self._first_violation(prob, xs) <= self.p.unsafe_tol
