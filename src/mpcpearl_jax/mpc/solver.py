"""Host-side SQP for the risk-aware MPC (paper eq. (4), method §6) on OSQP.

Each QP linearizes, around the current plan, the bicycle dynamics (eq. (3b)), the static
obstacles as tangent half-planes of the rounded-box distance (eq. (4c)) and the safety loss of
every GP sample (eq. (4b), SAA-CVaR in epigraph form). Variables, in this order:

  u_k [K, 2] (physical v, delta), X_k = x_{t+k+1|t} [K, 3], xi_k [K], s_kj [K, T],
  static slacks e_kj [K, S], CVaR slacks c_k [K]

The safety loss of sample m is linearized at its active person (the max in L). Only the T samples
with the largest loss at the current plan per stage enter the QP (`qp_tail_samples`; the CVaR at
alpha = 0.95 only sees the top M (1 - alpha) = 5 of them); samples below the VaR contribute zero
to the CVaR sum, and the line search and the safety check use the exact SAA-CVaR over all M.

The sparsity pattern is built once per problem size; each solve only updates values in place
(and restarts OSQP's rho, so that no solver state carries from one QP to the next), warm-starts
from the shifted previous plan, bounds the inputs by a trust region and accepts steps
by a line search on the exact SAA merit (cost + slack_penalty * violations).
"""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import time
from typing import NamedTuple

import numpy as np
import osqp
import scipy.sparse as sp

from mpcpearl_jax.envs.types import NavConfig
from mpcpearl_jax.mpc import model
from mpcpearl_jax.mpc.config import MPCConfig

# An unconverged QP still gives a search direction: the line search on the exact merit decides.
_OK_STATUS = (
    osqp.SolverStatus.OSQP_SOLVED,
    osqp.SolverStatus.OSQP_SOLVED_INACCURATE,
    osqp.SolverStatus.OSQP_MAX_ITER_REACHED,
)


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


@dataclasses.dataclass(frozen=True)
class SolverParams:
    """Plain numbers the host solver needs (picklable for worker processes)."""

    horizon: int
    num_samples: int
    qp_samples: int  # T, samples per stage in the QP
    num_static: int
    dt: float
    wheelbase: float
    v_max: float
    steer_max: float
    eps_dynamic: float  # r_r + r_d + r_safe, centre distance to a person
    static_margin: float  # r_r + r_safe, clearance to an obstacle surface
    q_weight: float
    r_weight: float
    terminal_weight: float
    alpha: float
    delta_cvar: float
    trust_v: float
    trust_steer: float
    slack_penalty: float
    sqp_iters: int
    sqp_step_tol: float
    line_search_steps: int
    cold_speed: float
    unsafe_tol: float
    unsafe_recovery: bool
    multi_start: str
    osqp_settings: tuple[tuple[str, float | int | bool], ...]


def solver_params(cfg: MPCConfig, nav: NavConfig, num_static: int) -> SolverParams:
    """Resolve the MPC config against the env config (r_safe, v_max, weights, thresholds)."""
    r_safe = nav.r_safe if cfg.r_safe is None else cfg.r_safe
    v_max = nav.v_max if cfg.v_max is None else min(cfg.v_max, nav.v_max)
    osqp_settings = (
        ("eps_abs", cfg.osqp_eps_abs),
        ("eps_rel", cfg.osqp_eps_rel),
        ("max_iter", cfg.osqp_max_iter),
        ("rho", cfg.osqp_rho),
        ("check_termination", cfg.osqp_check_termination),
        ("adaptive_rho_interval", cfg.osqp_adaptive_rho_interval),
        ("polishing", cfg.osqp_polish),
        ("warm_starting", True),
        ("verbose", False),
    )
    return SolverParams(
        horizon=cfg.horizon,
        num_samples=cfg.num_samples,
        qp_samples=min(cfg.qp_tail_samples, cfg.num_samples),
        num_static=num_static,
        dt=nav.dt,
        wheelbase=nav.wheelbase,
        v_max=v_max,
        steer_max=cfg.steer_max,
        eps_dynamic=nav.robot_radius + nav.human_radius + r_safe,
        static_margin=nav.robot_radius + r_safe,
        q_weight=nav.q_weight,
        r_weight=nav.r_weight,
        terminal_weight=cfg.terminal_weight,
        alpha=cfg.alpha,
        delta_cvar=cfg.delta_cvar,
        trust_v=cfg.trust_v,
        trust_steer=cfg.trust_steer,
        slack_penalty=cfg.slack_penalty,
        sqp_iters=cfg.sqp_iters,
        sqp_step_tol=cfg.sqp_step_tol,
        line_search_steps=cfg.line_search_steps,
        cold_speed=min(cfg.cold_speed, v_max),
        unsafe_tol=cfg.unsafe_tol,
        unsafe_recovery=cfg.unsafe_recovery,
        multi_start=cfg.multi_start,
        osqp_settings=osqp_settings,
    )


class RowProblem(NamedTuple):
    """One env's MPC problem. samples: [K, N_adapt, M, 2] GP samples of people at stages 1..K;
    valid: [N_adapt] bool (a False person never constrains); static_*: [S, 2], [S, 2], [S]."""

    x0: np.ndarray
    goal: np.ndarray
    samples: np.ndarray
    valid: np.ndarray
    static_lo: np.ndarray
    static_hi: np.ndarray
    static_radius: np.ndarray


class SolveResult(NamedTuple):
    """u: [K, 2] physical plan; poses: [K + 1, 3]; ok: the plan is safe to apply.

    stop: why the SQP that gave the plan ended (`SQP_STOPS`): "converged" (an accepted step below
    `sqp_step_tol`), "stalled" (the line search found no decrease), "capped" (`sqp_iters` QPs
    without either: the plan is the best iterate, the last accepted one) or "qp_failed"."""

    u: np.ndarray
    poses: np.ndarray
    ok: bool
    reason: str  # "solved" | "least_violation" | "qp_failed" | "unsafe" | "nonfinite"
    qp_iters: int
    n_qp: int
    solve_time: float
    merit: float
    stop: str = "converged"
    start: str = "warm"  # the start the plan came from (`START_NAMES`)


SQP_STOPS = ("converged", "stalled", "capped", "qp_failed")
# the SQP's starting plans (`multi_start`): the caller's plan (the shifted previous plan, or the
# cold start where it has none), the cold start, and standing still
START_NAMES = ("warm", "cold", "stop")


class SQPRun(NamedTuple):
    """One SQP from one start: plan u [K, 2], poses xs [K + 1, 3], its exact merit, QP
    iterations, QPs, reason (as `SolveResult.reason`) and stop (`SQP_STOPS`)."""

    u: np.ndarray
    xs: np.ndarray
    merit: float
    qp_iters: int
    n_qp: int
    reason: str
    stop: str


class _Layout:
    """Variable and row offsets of the QP (see module docstring)."""

    def __init__(self, p: SolverParams):
        k, m, s = p.horizon, p.qp_samples, p.num_static
        self.u = 0
        self.x = 2 * k
        self.xi = self.x + 3 * k
        self.s = self.xi + k
        self.es = self.s + k * m
        self.ec = self.es + k * s
        self.n = self.ec + k
        self.r_dyn = 0
        self.r_u = 3 * k
        self.r_spos = self.r_u + 2 * k
        self.r_samp = self.r_spos + k * m
        self.r_cvar = self.r_samp + k * m
        self.r_stat = self.r_cvar + k
        self.r_slk = self.r_stat + k * s
        self.m = self.r_slk + k * s + k


def _pattern(p: SolverParams, lay: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of every constraint entry in the order `_values` produces them."""
    k_, m_, s_ = p.horizon, p.qp_samples, p.num_static
    K, I3, J3 = np.meshgrid(np.arange(k_), np.arange(3), np.arange(3), indexing="ij")
    rows, cols = [], []

    def add(r, c):
        rows.append(np.broadcast_to(r, np.broadcast(r, c).shape).ravel())
        cols.append(np.broadcast_to(c, np.broadcast(r, c).shape).ravel())

    kk = np.arange(k_)
    add(lay.r_dyn + 3 * kk[:, None] + np.arange(3), lay.x + 3 * kk[:, None] + np.arange(3))
    add(lay.r_dyn + 3 * K[1:] + I3[1:], lay.x + 3 * (K[1:] - 1) + J3[1:])  # -A_k
    kb, ib, jb = np.meshgrid(kk, np.arange(3), np.arange(2), indexing="ij")
    add(lay.r_dyn + 3 * kb + ib, lay.u + 2 * kb + jb)  # -B_k
    add(lay.r_u + np.arange(2 * k_), lay.u + np.arange(2 * k_))
    add(lay.r_spos + np.arange(k_ * m_), lay.s + np.arange(k_ * m_))
    ks, ms = np.meshgrid(kk, np.arange(m_), indexing="ij")
    samp_rows = lay.r_samp + ks * m_ + ms
    add(samp_rows, lay.s + ks * m_ + ms)
    add(samp_rows, lay.xi + ks)
    add(samp_rows, lay.x + 3 * ks)
    add(samp_rows, lay.x + 3 * ks + 1)
    add(lay.r_cvar + kk, lay.xi + kk)
    add(lay.r_cvar + kk[:, None], lay.s + kk[:, None] * m_ + np.arange(m_))
    add(lay.r_cvar + kk, lay.ec + kk)
    kt, jt = np.meshgrid(kk, np.arange(s_), indexing="ij")
    stat_rows = lay.r_stat + kt * s_ + jt
    add(stat_rows, lay.x + 3 * kt)
    add(stat_rows, lay.x + 3 * kt + 1)
    add(stat_rows, lay.es + kt * s_ + jt)
    add(lay.r_slk + np.arange(k_ * s_ + k_), lay.es + np.arange(k_ * s_ + k_))
    return np.concatenate(rows), np.concatenate(cols)


class Linearization(NamedTuple):
    """Everything one QP needs from the current plan."""

    a: np.ndarray  # [K, 3, 3]
    b: np.ndarray  # [K, 3, 2]
    dyn_rhs: np.ndarray  # [K, 3]
    samp_grad: np.ndarray  # [K, T, 2] gradient of |p - q| (active person) at the plan
    samp_lo: np.ndarray  # [K, T] lower bound of s + xi + grad . p (-inf: nobody constrains)
    stat_grad: np.ndarray  # [K, S, 2]
    stat_lo: np.ndarray  # [K, S]


def _tail_samples(p: SolverParams, prob: RowProblem, pos: np.ndarray):
    """Gradient [K, T, 2] and distance [K, T] (inf if nobody is valid) of the T samples per stage
    with the largest safety loss at the plan positions pos [K, 2], each at its active person."""
    d, g = model.point_distance(pos[:, None, None, :], prob.samples)  # [K, NA, M], [K, NA, M, 2]
    d = np.where(prob.valid[None, :, None], d, np.inf)
    active = np.argmin(d, axis=1)[:, None]  # [K, 1, M]: max loss = min distance
    d_act = np.take_along_axis(d, active, axis=1)[:, 0]  # [K, M]
    g_act = np.take_along_axis(g, active[..., None], axis=1)[:, 0]  # [K, M, 2]
    top = np.argsort(d_act, axis=1)[:, : p.qp_samples]  # [K, T]
    return np.take_along_axis(g_act, top[..., None], axis=1), np.take_along_axis(d_act, top, axis=1)


def linearize_problem(p: SolverParams, prob: RowProblem, u: np.ndarray, xs: np.ndarray):
    """Linearize dynamics and constraints at the plan (u [K, 2], xs [K + 1, 3] from x0)."""
    a, b = model.linearize(xs[:-1], u, p.dt, p.wheelbase)
    f = xs[1:]  # xs is the nonlinear rollout of u, so f(xbar_k, ubar_k) = xbar_{k+1}
    dyn_rhs = f - np.einsum("kij,kj->ki", b, u)
    dyn_rhs[1:] -= np.einsum("kij,kj->ki", a[1:], xs[1:-1])
    pos = xs[1:, :2]  # [K, 2]
    g, d = _tail_samples(p, prob, pos)
    # L_lin = eps_d - d - g.(p - pbar) <= s + xi  <=>  s + xi + g.p >= eps_d - d + g.pbar
    samp_lo = p.eps_dynamic - d + np.einsum("ktj,kj->kt", g, pos)
    bd, bg = model.box_distance(pos[:, None, :], prob.static_lo, prob.static_hi)
    need = p.static_margin + prob.static_radius[None, :]
    stat_lo = need - bd + np.einsum("ksj,kj->ks", bg, pos)
    return Linearization(a, b, dyn_rhs, g, samp_lo, bg, stat_lo)


def _values(p: SolverParams, lin: Linearization) -> np.ndarray:
    """Constraint-matrix entries in the order of `_pattern`."""
    k_, m_, s_ = p.horizon, p.qp_samples, p.num_static
    ones = np.ones
    parts = [
        ones(3 * k_),
        -lin.a[1:].ravel(),
        -lin.b.ravel(),
        ones(2 * k_),
        ones(k_ * m_),
        ones(k_ * m_),
        ones(k_ * m_),
        lin.samp_grad[..., 0].ravel(),
        lin.samp_grad[..., 1].ravel(),
        ones(k_),
        np.full(k_ * m_, 1.0 / (p.num_samples * (1.0 - p.alpha))),
        -ones(k_),
        lin.stat_grad[..., 0].ravel(),
        lin.stat_grad[..., 1].ravel(),
        ones(k_ * s_),
        ones(k_ * s_ + k_),
    ]
    return np.concatenate(parts)


def _bounds(p: SolverParams, lay: _Layout, lin: Linearization, u: np.ndarray):
    """Row bounds l, u [m] of the QP at the plan u [K, 2] (trust region in the input rows)."""
    lo = np.full(lay.m, -np.inf)
    hi = np.full(lay.m, np.inf)
    lo[: 3 * p.horizon] = hi[: 3 * p.horizon] = lin.dyn_rhs.ravel()
    box_lo = np.array([0.0, -p.steer_max])
    box_hi = np.array([p.v_max, p.steer_max])
    trust = np.array([p.trust_v, p.trust_steer])
    lo[lay.r_u : lay.r_spos] = np.maximum(box_lo, u - trust).ravel()
    hi[lay.r_u : lay.r_spos] = np.minimum(box_hi, u + trust).ravel()
    lo[lay.r_spos : lay.r_samp] = 0.0
    lo[lay.r_samp : lay.r_cvar] = lin.samp_lo.ravel()
    hi[lay.r_cvar : lay.r_stat] = p.delta_cvar
    lo[lay.r_stat : lay.r_slk] = lin.stat_lo.ravel()
    lo[lay.r_slk :] = 0.0
    return lo, hi


def stage_weights(p: SolverParams) -> np.ndarray:
    """Position weight of X_k = x_{t+k+1|t}, k = 0..K-1 (terminal weight on the last) [K]."""
    w = np.full(p.horizon, p.q_weight)
    w[-1] = p.terminal_weight * p.q_weight
    return w


def safety_losses(p: SolverParams, prob: RowProblem, pos: np.ndarray) -> np.ndarray:
    """Safety loss L = max_i (eps_d - |p_k - q_kim|) over valid people [K, M] (-inf if none)."""
    d = np.linalg.norm(pos[:, None, None, :] - prob.samples, axis=-1)  # [K, NA, M]
    loss = np.where(prob.valid[None, :, None], p.eps_dynamic - d, -np.inf)
    return loss.max(axis=1)


def violations(p: SolverParams, prob: RowProblem, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact violations of the plan at stages 1..K: static [K, S] (eq. (4c)) and CVaR
    excess [K] (eq. (4b) with the exact SAA-CVaR), both >= 0."""
    pos = xs[1:, :2]
    bd, _ = model.box_distance(pos[:, None, :], prob.static_lo, prob.static_hi)
    static = np.maximum(p.static_margin + prob.static_radius[None, :] - bd, 0.0)
    if not prob.valid.any():
        return static, np.zeros(p.horizon)
    cvar = model.saa_cvar(safety_losses(p, prob, pos), p.alpha)
    return static, np.maximum(cvar - p.delta_cvar, 0.0)


def merit(p: SolverParams, prob: RowProblem, u: np.ndarray, xs: np.ndarray) -> float:
    """Exact SAA merit: stage + terminal cost + slack_penalty * (static + CVaR violations)."""
    err = np.sum((xs[1:, :2] - prob.goal) ** 2, axis=-1)
    cost = np.dot(stage_weights(p), err) + p.r_weight * np.sum(u * u)
    static, cvar = violations(p, prob, xs)
    return float(cost + p.slack_penalty * (static.sum() + cvar.sum()))


def clip_inputs(p: SolverParams, u: np.ndarray) -> np.ndarray:
    """Project inputs [K, 2] onto the MPC input box (eq. (3e))."""
    return np.clip(u, [0.0, -p.steer_max], [p.v_max, p.steer_max])


def cold_start(p: SolverParams, prob: RowProblem) -> np.ndarray:
    """Cold-start plan [K, 2]: constant speed, steering towards the goal."""
    to_goal = prob.goal - prob.x0[:2]
    err = np.arctan2(to_goal[1], to_goal[0]) - prob.x0[2]
    err = (err + np.pi) % (2 * np.pi) - np.pi
    u = np.zeros((p.horizon, 2))
    u[:, 0] = p.cold_speed
    u[:, 1] = np.clip(err, -0.5, 0.5)
    return u


def stop_start(p: SolverParams) -> np.ndarray:
    """The standing-still plan [K, 2]: zero speed, straight wheels."""
    return np.zeros((p.horizon, 2))


def starts(
    p: SolverParams, prob: RowProblem, u_init: np.ndarray | None
) -> list[tuple[str, np.ndarray]]:
    """The SQP's starting plans in order: (name, u [K, 2]); the caller's plan first (the cold
    start if it has none), then the other starts of `START_NAMES`."""
    cold = cold_start(p, prob)
    first = [("warm", np.asarray(u_init, float))] if u_init is not None else [("cold", cold)]
    rest = [("cold", cold)] if u_init is not None else []
    return first + rest + [("stop", stop_start(p))]


class SQPSolver:
    """SQP on OSQP with a fixed sparsity pattern, for problems of one size (K, M, N_adapt, S)."""

    def __init__(self, params: SolverParams):
        self.p = params
        self.lay = _Layout(params)
        self._cost_scale = 1.0 / params.slack_penalty  # QP objective in units of the penalty
        rows, cols = _pattern(params, self.lay)
        order = sp.csc_matrix(
            (np.arange(1, rows.size + 1, dtype=float), (rows, cols)), shape=(self.lay.m, self.lay.n)
        )
        if order.nnz != rows.size:
            raise AssertionError("duplicate entries in the QP pattern")
        self._perm = order.data.astype(np.int64) - 1  # CSC slot -> triplet index
        self._indices, self._indptr = order.indices.copy(), order.indptr.copy()
        self._P = self._cost_matrix()
        self._osqp: osqp.OSQP | None = None
        self._rho = float(dict(params.osqp_settings)["rho"])

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

    def _matrix(self, values: np.ndarray) -> sp.csc_matrix:
        data = values[self._perm]
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
        """One QP at the plan; returns (u_qp [K, 2] or None, status, iterations)."""
        lin = linearize_problem(self.p, prob, u, xs)
        values = _values(self.p, lin)
        lo, hi = _bounds(self.p, self.lay, lin, u)
        q = self._linear_cost(prob.goal)
        if self._osqp is None:
            self._osqp = osqp.OSQP()
            self._osqp.setup(self._P, q, self._matrix(values), lo, hi, **dict(self.p.osqp_settings))
        else:
            # OSQP keeps the step size rho its adaptive scheme reached in the previous solve:
            # restart every QP from the configured rho, so that a solve depends on its own
            # inputs only (not on which rows this solver met before; exact resume, workers)
            self._osqp.update_settings(rho=self._rho)
            self._osqp.update(q=q, l=lo, u=hi, Ax=values[self._perm])
        guess = self._primal_guess(lin, u, xs)
        res = solve_through_stops(self._osqp, guess, np.zeros(self.lay.m), self._rho)
        status = res.info.status_val
        if (
            status not in _OK_STATUS
            or res.x is None
            or not np.all(np.isfinite(res.x[: self.lay.xi]))
        ):
            return None, int(status), int(res.info.iter)
        return res.x[self.lay.u : self.lay.x].reshape(-1, 2), int(status), int(res.info.iter)

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
            u_qp, status, it = self._solve_qp(prob, u, xs)
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


_WORKER_SOLVERS: dict[SolverParams, SQPSolver] = {}


def solve_in_worker(
    params: SolverParams, prob: RowProblem, u_init: np.ndarray | None
) -> SolveResult:
    """Entry point for process-pool workers: one cached solver per problem size."""
    solver = _WORKER_SOLVERS.get(params)
    if solver is None:
        solver = _WORKER_SOLVERS[params] = SQPSolver(params)
    return solver.solve(prob, u_init)


# the signals a user stops a training with: Ctrl-C (to the terminal's whole process group), a closed
# terminal, `kill` or a scheduler's SIGTERM (possibly to the whole group)
STOP_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)
)


def pool_worker_init(parent_pid: int) -> None:
    """Pool-worker initializer: the worker leaves the training's process group and ignores
    Ctrl-C and a closed terminal, so a stop signal reaches the training process only, which
    saves and shuts its pool down (a worker killed by the signal would break the pool);
    `watch_parent` ends the worker if the training process is gone. The pool starts its
    workers with the stop signals blocked (`MPCBridge`), so one sent before this runs waits:
    SIGINT and SIGHUP are then ignored, and a SIGTERM sent to the old group is dropped."""
    import os

    with contextlib.suppress(OSError):
        os.setpgid(0, 0)
    for s in STOP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)  # ignoring a blocked, pending signal discards it
    if hasattr(signal, "SIGTERM"):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the pool's own terminate() works
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    watch_parent(parent_pid)


def watch_parent(parent_pid: int, interval_s: float = 2.0) -> None:
    """Pool-worker initializer: exit when the training process is gone (killed with SIGKILL or
    SIGTERM, no chance to shut the pool down), instead of lingering as an orphan."""
    import os
    import threading

    def watch() -> None:
        while True:
            time.sleep(interval_s)
            if os.getppid() != parent_pid:
                os._exit(0)

    threading.Thread(target=watch, daemon=True, name="watch-parent").start()
