"""The risk-aware MPC's problem (paper eq. (4), method §6) in NumPy: what the host SQP solves
(`mpc.sqp`), without the QP solver itself or its settings (`mpc.qp`, `mpc.qp_osqp`).

One row's problem (`RowProblem`) and the solver's settings resolved against the env
(`SolverParams`, `solver_params`); the SQP's starting plans (`cold_start`, `stop_start`,
`starts`); the exact SAA merit and violations the line search and the safety check use (`merit`,
`violations`, `safety_losses`); and the QP of one SQP iteration, linearized around the current
plan (`linearize_problem`, `QPLayout`, `qp_pattern`, `qp_values`, `qp_bounds`): the bicycle
dynamics (eq. (3b)), the static obstacles as tangent half-planes of the rounded-box distance
(eq. (4c)) and the safety loss of every GP sample (eq. (4b), SAA-CVaR in epigraph form).
Variables of the QP, in this order:

  u_k [K, 2] (physical v, delta), X_k = x_{t+k+1|t} [K, 3], xi_k [K], s_kj [K, T],
  static slacks e_kj [K, S], CVaR slacks c_k [K]

The safety loss of sample m is linearized at its active person (the max in L). Only the T samples
with the largest loss at the current plan per stage enter the QP (`qp_tail_samples`; the CVaR at
alpha = 0.95 only sees the top M (1 - alpha) = 5 of them); samples below the VaR contribute zero
to the CVaR sum, and the line search and the safety check use the exact SAA-CVaR over all M.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from mpcpearl_jax.envs.types import NavConfig
from mpcpearl_jax.mpc import model
from mpcpearl_jax.mpc.config import MPCConfig


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


def solver_params(cfg: MPCConfig, nav: NavConfig, num_static: int) -> SolverParams:
    """Resolve the MPC config against the env config (r_safe, v_max, weights, thresholds); the
    QP solver's own settings are not part of the problem (`qp_osqp.OSQPSettings.from_config`)."""
    r_safe = nav.r_safe if cfg.r_safe is None else cfg.r_safe
    v_max = nav.v_max if cfg.v_max is None else min(cfg.v_max, nav.v_max)
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
    # "solved" | "least_violation" | "qp_failed" | "unsafe" | "nonfinite", or "worker_lost" (the
    # pool worker solving it died or ran past `MPCConfig.worker_timeout_s`: `mpc.host`)
    reason: str
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


class QPLayout:
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


def qp_pattern(p: SolverParams, lay: QPLayout) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of every constraint entry in the order `qp_values` produces them."""
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


def qp_values(p: SolverParams, lin: Linearization) -> np.ndarray:
    """Constraint-matrix entries in the order of `qp_pattern`."""
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


def qp_bounds(p: SolverParams, lay: QPLayout, lin: Linearization, u: np.ndarray):
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
