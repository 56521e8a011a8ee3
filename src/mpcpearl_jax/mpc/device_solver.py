"""The SQP of the risk-aware MPC (paper eq. (4), method §6) in JAX: jit- and vmap-able.

The same SQP as the host solver on OSQP (`mpcpearl_jax.mpc.solver`, the reference): each QP
linearizes, around the current plan, the bicycle dynamics (eq. (3b)), the static obstacles as
tangent half-planes of the rounded-box distance (eq. (4c)) and the safety loss of the `qp_samples`
GP samples per stage with the largest loss (eq. (4b), SAA-CVaR in epigraph form); the inputs are
bounded by the box (eq. (3e)) and the trust region; steps are accepted by a backtracking line
search on the exact SAA merit (cost + slack_penalty * violations).

Differences of form, not of problem:
  - the dynamics equality constraints are condensed: the states are affine in the inputs,
    X = M u + c, so a QP's variables are u [K, 2], xi [K], s [K, T], e [K, S], c [K];
  - each QP is solved by the batched interior-point method of `qpax` (dense, float32, a fixed
    number of iterations) instead of OSQP's ADMM;
  - the SQP runs its fixed `sqp_iters` iterations with masks in place of an early `break`, and
    the unsafe-plan recovery runs only when some row of the batch needs it (`lax.cond`).

Reasons are ints (`REASONS`): the same decisions as the host solver's strings.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.mpc.solver import RowProblem, SolverParams

REASONS = ("solved", "least_violation", "unsafe", "qp_failed", "nonfinite")
SOLVED, LEAST_VIOLATION, UNSAFE, QP_FAILED, NONFINITE = range(len(REASONS))
# a linearized sample row with nobody to constrain (lower bound -inf on the host) gets this
# loose bound instead: an interior point needs finite rows
_LOOSE = 1e3


class DeviceResult(NamedTuple):
    """Batched (leading axis B) or per-row: u [K, 2] physical plan, poses [K + 1, 3], ok (safe
    to apply), reason (index into REASONS), qp_iters (interior-point iterations), n_qp, merit."""

    u: Array
    poses: Array
    ok: Array
    reason: Array
    qp_iters: Array
    n_qp: Array
    merit: Array


# ----------------------------------------------------------------------------- model (eq. (3))
def _slip(delta: Array) -> Array:
    return jnp.arctan2(jnp.sin(delta), 2.0 * jnp.cos(delta))


def bicycle_step(p: SolverParams, pose: Array, u: Array) -> Array:
    """Unwrapped Euler step of the bicycle model (eq. (3b)); pose [3], u [2] physical."""
    beta = _slip(u[1])
    x = pose[0] + p.dt * u[0] * jnp.cos(pose[2] + beta)
    y = pose[1] + p.dt * u[0] * jnp.sin(pose[2] + beta)
    th = pose[2] + p.dt * u[0] * 2.0 * jnp.sin(beta) / p.wheelbase
    return jnp.stack([x, y, th])


def rollout(p: SolverParams, x0: Array, u: Array) -> Array:
    """Poses [K + 1, 3] of the plan u [K, 2] from x0 [3] (poses[0] = x0)."""

    def step(pose, uk):
        nxt = bicycle_step(p, pose, uk)
        return nxt, nxt

    _, xs = jax.lax.scan(step, x0, u)
    return jnp.concatenate([x0[None], xs], axis=0)


def jacobians(p: SolverParams, pose: Array, u: Array) -> tuple[Array, Array]:
    """A = df/dx [..., 3, 3] and B = df/du [..., 3, 2] of the unwrapped step (eq. (3b))."""
    f = lambda x, v: bicycle_step(p, x, v)  # noqa: E731
    jac = jax.vmap(jax.jacfwd(f, argnums=(0, 1)))
    return jac(pose, u)


# ------------------------------------------------------------------ constraints (eq. (4b), (4c))
def box_distance(pt: Array, lo: Array, hi: Array) -> tuple[Array, Array]:
    """Distance [...] of points pt [..., 2] to boxes [lo, hi] and its gradient [..., 2] (inside a
    box: 0 and the unit vector away from its centre), as `mpc.model.box_distance`."""
    diff = pt - jnp.clip(pt, lo, hi)
    dist = jnp.linalg.norm(diff, axis=-1)
    away = pt - 0.5 * (lo + hi)
    away_n = jnp.linalg.norm(away, axis=-1, keepdims=True)
    unit = jnp.array([1.0, 0.0], pt.dtype)
    away = jnp.where(away_n > 1e-9, away / jnp.maximum(away_n, 1e-12), unit)
    grad = jnp.where(dist[..., None] <= 1e-9, away, diff / jnp.maximum(dist, 1e-12)[..., None])
    return dist, grad


def saa_cvar(p: SolverParams, losses: Array) -> Array:
    """Exact SAA-CVaR of losses [..., M] (eq. (4b)): the top M (1 - alpha) mean, with a
    fractional weight on the boundary sample (as `mpc.model.saa_cvar`)."""
    m = losses.shape[-1]
    srt = -jnp.sort(-losses, axis=-1)
    tail = m * (1.0 - p.alpha)
    n_full = int(tail + 1e-9)
    total = srt[..., :n_full].sum(axis=-1)
    if tail - n_full > 1e-9 and n_full < m:
        total = total + (tail - n_full) * srt[..., n_full]
    return total / tail


def violations(p: SolverParams, prob: RowProblem, xs: Array) -> tuple[Array, Array]:
    """Exact violations at stages 1..K: static [K, S] (eq. (4c)) and CVaR excess [K] (eq. (4b)
    with the exact SAA-CVaR over all M samples), both >= 0."""
    pos = xs[1:, :2]
    bd, _ = box_distance(pos[:, None, :], prob.static_lo, prob.static_hi)
    static = jnp.maximum(p.static_margin + prob.static_radius[None, :] - bd, 0.0)
    d = jnp.linalg.norm(pos[:, None, None, :] - prob.samples, axis=-1)  # [K, NA, M]
    loss = jnp.where(prob.valid[None, :, None], p.eps_dynamic - d, -jnp.inf).max(axis=1)
    cvar = jnp.maximum(saa_cvar(p, loss) - p.delta_cvar, 0.0)
    return static, jnp.where(jnp.any(prob.valid), cvar, 0.0)


def first_violation(p: SolverParams, prob: RowProblem, xs: Array) -> Array:
    """The larger first-stage violation of eq. (4c) and eq. (4b) (>= 0; NaN stays NaN)."""
    static, cvar = violations(p, prob, xs)
    return jnp.maximum(jnp.max(static[0], initial=0.0), cvar[0])


def stage_weights(p: SolverParams) -> Array:
    """Position weight [K] of X_k (terminal weight on the last), eq. (4a)."""
    w = jnp.full((p.horizon,), p.q_weight, jnp.float32)
    return w.at[-1].set(p.terminal_weight * p.q_weight)


def merit(p: SolverParams, prob: RowProblem, u: Array, xs: Array) -> Array:
    """Exact SAA merit (eq. (4a) cost + slack_penalty * violations of eq. (4b), (4c))."""
    err = jnp.sum((xs[1:, :2] - prob.goal) ** 2, axis=-1)
    cost = jnp.dot(stage_weights(p), err) + p.r_weight * jnp.sum(u * u)
    static, cvar = violations(p, prob, xs)
    return cost + p.slack_penalty * (static.sum() + cvar.sum())


# --------------------------------------------------------------------------- plans
def clip_inputs(p: SolverParams, u: Array) -> Array:
    """Project inputs [K, 2] onto the input box (eq. (3e))."""
    return jnp.clip(u, jnp.array([0.0, -p.steer_max]), jnp.array([p.v_max, p.steer_max]))


def cold_start(p: SolverParams, prob: RowProblem) -> Array:
    """Constant speed, steering towards the goal [K, 2] (as the host solver's cold start)."""
    to_goal = prob.goal - prob.x0[:2]
    err = jnp.arctan2(to_goal[1], to_goal[0]) - prob.x0[2]
    err = jnp.mod(err + jnp.pi, 2 * jnp.pi) - jnp.pi
    row = jnp.stack([jnp.asarray(p.cold_speed, err.dtype), jnp.clip(err, -0.5, 0.5)])
    return jnp.broadcast_to(row, (p.horizon, 2))


# ------------------------------------------------------------------------ the QP (eq. (4))
class Linearization(NamedTuple):
    """Condensed dynamics X = m u + c (m [K, 3, 2K], c [K, 3]) and the linearized rows."""

    m: Array
    c: Array
    samp_grad: Array  # [K, T, 2]
    samp_lo: Array  # [K, T] (finite; _LOOSE below where nobody constrains)
    stat_grad: Array  # [K, S, 2]
    stat_lo: Array  # [K, S]


def condense(a: Array, b: Array, rhs: Array) -> tuple[Array, Array]:
    """X_k = A_k X_{k-1} + B_k u_k + rhs_k (X_{-1} = 0) as X = m u + c (eq. (3b) linearized)."""
    k = a.shape[0]
    a = a.at[0].set(0.0)  # the first stage starts from x0, folded into rhs_0
    sel = jnp.eye(2 * k, dtype=b.dtype).reshape(k, 2, 2 * k)

    def step(carry, inp):
        m_prev, c_prev = carry
        ak, bk, rk, ek = inp
        m_k = ak @ m_prev + bk @ ek
        c_k = ak @ c_prev + rk
        return (m_k, c_k), (m_k, c_k)

    init = (jnp.zeros((3, 2 * k), b.dtype), jnp.zeros(3, b.dtype))
    _, (m, c) = jax.lax.scan(step, init, (a, b, rhs, sel))
    return m, c


def tail_samples(p: SolverParams, prob: RowProblem, pos: Array) -> tuple[Array, Array]:
    """Gradient [K, T, 2] and distance [K, T] (inf where nobody is valid) of the T samples per
    stage with the largest safety loss at pos [K, 2], each at its active person (eq. (4b))."""
    diff = pos[:, None, None, :] - prob.samples  # [K, NA, M, 2]
    d = jnp.linalg.norm(diff, axis=-1)
    g = diff / jnp.maximum(d, 1e-9)[..., None]
    d = jnp.where(prob.valid[None, :, None], d, jnp.inf)
    active = jnp.argmin(d, axis=1)[:, None]  # [K, 1, M]
    d_act = jnp.take_along_axis(d, active, axis=1)[:, 0]
    g_act = jnp.take_along_axis(g, active[..., None], axis=1)[:, 0]
    _, top = jax.lax.top_k(-d_act, p.qp_samples)  # [K, T] smallest distances
    return jnp.take_along_axis(g_act, top[..., None], axis=1), jnp.take_along_axis(d_act, top, 1)


def linearize(p: SolverParams, prob: RowProblem, u: Array, xs: Array) -> Linearization:
    """Linearize dynamics and constraints at the plan (u [K, 2], xs its rollout [K + 1, 3])."""
    a, b = jacobians(p, xs[:-1], u)
    rhs = xs[1:] - jnp.einsum("kij,kj->ki", b, u)
    rhs = rhs.at[1:].add(-jnp.einsum("kij,kj->ki", a[1:], xs[1:-1]))
    m, c = condense(a, b, rhs)
    pos = xs[1:, :2]
    g, d = tail_samples(p, prob, pos)
    samp_lo = p.eps_dynamic - d + jnp.einsum("ktj,kj->kt", g, pos)
    nobody = jnp.isinf(d) & (d > 0)
    samp_lo = jnp.where(nobody, -_LOOSE, samp_lo)
    g = jnp.where(nobody[..., None], 0.0, g)
    bd, bg = box_distance(pos[:, None, :], prob.static_lo, prob.static_hi)
    need = p.static_margin + prob.static_radius[None, :]
    stat_lo = need - bd + jnp.einsum("ksj,kj->ks", bg, pos)
    return Linearization(m, c, g, samp_lo, bg, stat_lo)


def qp_cost(p: SolverParams, lin: Linearization, goal: Array) -> tuple[Array, Array]:
    """Hessian [n, n] and gradient [n] of the QP objective (eq. (4a) in the inputs, the slacks'
    L1 penalty), in units of slack_penalty, over z = (u, xi, s, e, c)."""
    k, t, s = p.horizon, p.qp_samples, p.num_static
    mp, cp, w = lin.m[:, :2], lin.c[:, :2], stage_weights(p)
    q_uu = 2.0 * jnp.einsum("k,kiu,kiv->uv", w, mp, mp) + 2.0 * p.r_weight * jnp.eye(2 * k)
    q_u = 2.0 * jnp.einsum("k,kiu,ki->u", w, mp, cp - goal)
    n = 2 * k + k + k * t + k * s + k
    hess = jnp.zeros((n, n)).at[: 2 * k, : 2 * k].set(q_uu)
    hess = hess.at[jnp.arange(2 * k, 3 * k), jnp.arange(2 * k, 3 * k)].set(1e-3)
    grad = jnp.zeros(n).at[: 2 * k].set(q_u).at[3 * k + k * t :].set(p.slack_penalty)
    return hess / p.slack_penalty, grad / p.slack_penalty


def qp_constraints(p: SolverParams, lin: Linearization, u: Array) -> tuple[Array, Array]:
    """Rows G [r, n], h [r] of G z <= h: input box and trust region (eq. (3e)), s >= 0, the
    epigraph rows s + xi + g.p >= lo and the CVaR row per stage (eq. (4b)), the static
    half-planes with slacks (eq. (4c)), slacks >= 0."""
    k, t, s = p.horizon, p.qp_samples, p.num_static
    nu, n_s, n_e = 2 * k, k * t, k * s
    mp, cp = lin.m[:, :2], lin.c[:, :2]
    eye = jnp.eye
    stage_of = lambda rows: jnp.repeat(eye(k), rows, axis=0)  # noqa: E731  [k*rows, k]
    box_lo = jnp.array([0.0, -p.steer_max])
    box_hi = jnp.array([p.v_max, p.steer_max])
    trust = jnp.array([p.trust_v, p.trust_steer])
    u_lo = jnp.maximum(box_lo, u - trust).ravel()
    u_hi = jnp.minimum(box_hi, u + trust).ravel()
    g_samp = jnp.einsum("ktj,kju->ktu", lin.samp_grad, mp).reshape(n_s, nu)
    g_stat = jnp.einsum("ksj,kju->ksu", lin.stat_grad, mp).reshape(n_e, nu)
    h_samp = (lin.samp_lo - jnp.einsum("ktj,kj->kt", lin.samp_grad, cp)).ravel()
    h_stat = (lin.stat_lo - jnp.einsum("ksj,kj->ks", lin.stat_grad, cp)).ravel()
    zero = jnp.zeros
    wcv = 1.0 / (p.num_samples * (1.0 - p.alpha))
    blocks = [  # columns: u [nu], xi [k], s [n_s], e [n_e], c [k]
        ([eye(nu), zero((nu, k)), zero((nu, n_s)), zero((nu, n_e)), zero((nu, k))], u_hi),
        ([-eye(nu), zero((nu, k)), zero((nu, n_s)), zero((nu, n_e)), zero((nu, k))], -u_lo),
        ([zero((n_s, nu)), zero((n_s, k)), -eye(n_s), zero((n_s, n_e)), zero((n_s, k))], zero(n_s)),
        ([-g_samp, -stage_of(t), -eye(n_s), zero((n_s, n_e)), zero((n_s, k))], -h_samp),
        (
            [zero((k, nu)), eye(k), wcv * stage_of(t).T, zero((k, n_e)), -eye(k)],
            jnp.full(k, p.delta_cvar),
        ),
        ([-g_stat, zero((n_e, k)), zero((n_e, n_s)), -eye(n_e), zero((n_e, k))], -h_stat),
        ([zero((n_e, nu)), zero((n_e, k)), zero((n_e, n_s)), -eye(n_e), zero((n_e, k))], zero(n_e)),
        ([zero((k, nu)), zero((k, k)), zero((k, n_s)), zero((k, n_e)), -eye(k)], zero(k)),
    ]
    g_mat = jnp.concatenate([jnp.concatenate(cols, axis=1) for cols, _ in blocks], axis=0)
    return g_mat, jnp.concatenate([h for _, h in blocks])


def solve_qp(p: SolverParams, qp_iters: int, prob: RowProblem, u: Array, xs: Array):
    """One QP at the plan (eq. (4) linearized) by qpax's interior point -> (u_qp [K, 2], finite,
    interior-point iterations)."""
    import qpax

    lin = linearize(p, prob, u, xs)
    hess, grad = qp_cost(p, lin, prob.goal)
    g_mat, h = qp_constraints(p, lin, u)
    n = hess.shape[0]
    x, *_, iters = qpax.solve_qp(
        hess, grad, jnp.zeros((0, n)), jnp.zeros(0), g_mat, h, solver_tol=1e-5, max_iter=qp_iters
    )
    u_qp = x[: 2 * p.horizon].reshape(p.horizon, 2)
    return u_qp, jnp.all(jnp.isfinite(u_qp)), iters


# ------------------------------------------------------------------------------- the SQP
def line_search(p: SolverParams, prob: RowProblem, u: Array, du: Array, cur: Array):
    """Backtracking on the exact SAA merit with steps 1, 1/2, 1/4, ...: the first step whose
    merit is below cur -> (found, u_t, xs_t, merit_t, |step|_inf)."""
    steps = 0.5 ** jnp.arange(max(p.line_search_steps, 1), dtype=u.dtype)
    u_t = u[None] + steps[:, None, None] * du[None]
    xs_t = jax.vmap(lambda v: rollout(p, prob.x0, v))(u_t)
    m_t = jax.vmap(lambda v, x: merit(p, prob, v, x))(u_t, xs_t)
    better = m_t < cur
    i = jnp.argmax(better)
    size = jnp.max(jnp.abs(steps[i] * du))
    return jnp.any(better), u_t[i], xs_t[i], m_t[i], size


class _SQPState(NamedTuple):
    u: Array
    xs: Array
    cur: Array
    active: Array
    failed_first: Array
    qp_iters: Array
    n_qp: Array


def _sqp_iteration(p: SolverParams, qp_iters: int, prob: RowProblem, i: Array, st: _SQPState):
    """One SQP iteration, masked: a row that stopped (QP failed, no merit decrease, step below
    sqp_step_tol) keeps its state, as the host solver's `break`."""
    u_qp, finite, its = solve_qp(p, qp_iters, prob, st.u, st.xs)
    du = jnp.where(finite, clip_inputs(p, jnp.where(finite, u_qp, 0.0)) - st.u, 0.0)
    found, u_t, xs_t, m_t, size = line_search(p, prob, st.u, du, st.cur)
    take = st.active & finite & found
    return _SQPState(
        jnp.where(take, u_t, st.u),
        jnp.where(take, xs_t, st.xs),
        jnp.where(take, m_t, st.cur),
        take & (size >= p.sqp_step_tol),
        st.failed_first | (st.active & ~finite & (i == 0)),
        st.qp_iters + jnp.where(st.active, its, 0),
        st.n_qp + st.active.astype(jnp.int32),
    )


def sqp(p: SolverParams, qp_iters: int, prob: RowProblem, u: Array):
    """`sqp_iters` masked SQP iterations from u [K, 2] -> (u, xs, merit, reason, IP iterations,
    QPs); reason: qp_failed (first QP), nonfinite, unsafe (first stage, eq. (4b)/(4c) above
    unsafe_tol) or solved."""
    xs = rollout(p, prob.x0, u)
    zero = jnp.zeros((), jnp.int32)
    st = _SQPState(u, xs, merit(p, prob, u, xs), jnp.bool_(True), jnp.bool_(False), zero, zero)
    body = lambda i, s: _sqp_iteration(p, qp_iters, prob, i, s)  # noqa: E731
    st = jax.lax.fori_loop(0, p.sqp_iters, body, st)
    safe = first_violation(p, prob, st.xs) <= p.unsafe_tol  # False for NaN
    reason = jnp.where(
        st.failed_first,
        QP_FAILED,
        jnp.where(~jnp.all(jnp.isfinite(st.u)), NONFINITE, jnp.where(safe, SOLVED, UNSAFE)),
    ).astype(jnp.int32)
    return st.u, st.xs, st.cur, reason, st.qp_iters, st.n_qp


def grid_first_moves(p: SolverParams, prob: RowProblem, u: Array) -> tuple[Array, Array]:
    """The least first-stage violation over first inputs (0, v_max / 2, v_max) x (-max, 0, +max
    steering) with the rest of plan u, and that plan (the first of equals, as the host)."""
    vs = jnp.array([0.0, 0.5 * p.v_max, p.v_max])
    ds = jnp.array([-p.steer_max, 0.0, p.steer_max])
    firsts = jnp.stack(jnp.meshgrid(vs, ds, indexing="ij"), axis=-1).reshape(9, 2)
    plans = jnp.broadcast_to(u, (9, *u.shape)).at[:, 0].set(firsts)
    viol = jax.vmap(lambda v: first_violation(p, prob, rollout(p, prob.x0, v)))(plans)
    viol = jnp.where(jnp.isnan(viol), jnp.inf, viol)
    i = jnp.argmin(viol)
    return viol[i], jnp.where(jnp.isfinite(viol[i]), plans[i], u)


def recover(p: SolverParams, prob: RowProblem, first: tuple, second: tuple, best: Array):
    """The unsafe-plan recovery (extension `unsafe_recovery`) from the first SQP's result and the
    second's (run from the least violating first move, violation `best`): the second plan if
    solved, else the first of (first plan, second plan) whose first stage is as safe as that move
    (reason least_violation), else the first plan (unsafe); as the host solver's `solve`."""
    u, xs, cur, _, its, nq = first
    u2, xs2, cur2, reason2, its2, nq2 = second

    def fits(v, x):
        return jnp.all(jnp.isfinite(v)) & (first_violation(p, prob, x) <= best + p.unsafe_tol)

    use2 = (reason2 == SOLVED) | (~fits(u, xs) & fits(u2, xs2))
    least = (reason2 != SOLVED) & (fits(u, xs) | fits(u2, xs2))
    out_reason = jnp.where(reason2 == SOLVED, SOLVED, jnp.where(least, LEAST_VIOLATION, UNSAFE))
    pick = lambda a, b: jnp.where(use2, b, a)  # noqa: E731
    reason = out_reason.astype(jnp.int32)
    return (pick(u, u2), pick(xs, xs2), pick(cur, cur2), reason, its + its2, nq + nq2)


def _two_passes(p: SolverParams, run, probs: RowProblem, u0: Array):
    """The first SQP from u0 and, where some row is unsafe, the second from the least violating
    first moves, as one `lax.scan` over the two passes (the SQP is compiled once) ->
    (first, second, best first-move violation)."""
    grid = jax.vmap(lambda pr, u: grid_first_moves(p, pr, u))
    zeros = jax.tree_util.tree_map(
        lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(run, probs, u0)
    )

    def body(carry, i):
        first, start = carry
        need = (i == 0) | jnp.any(first[3] == UNSAFE)
        out = jax.lax.cond(need, lambda s: run(probs, s), lambda s: zeros, start)
        best, best_u = grid(probs, out[0])
        first = jax.tree_util.tree_map(lambda a, b: jnp.where(i == 0, b, a), first, out)
        return (first, jnp.where(i == 0, best_u, start)), (out, best)

    _, (outs, bests) = jax.lax.scan(body, (zeros, u0), jnp.arange(2))
    take = lambda j: jax.tree_util.tree_map(lambda a: a[j], outs)  # noqa: E731
    return take(0), take(1), bests[0]


def make_batch_solver(p: SolverParams, qp_iters: int) -> Callable[..., DeviceResult]:
    """`solve(probs, u_init, has_init) -> DeviceResult`, batched over a leading axis B of
    RowProblem (float32 arrays), u_init [B, K, 2] and has_init [B] bool (False: cold start).
    Jittable; the recovery pass (if `unsafe_recovery`) runs only when some row is unsafe."""
    run = jax.vmap(lambda prob, u: sqp(p, qp_iters, prob, u))
    start = jax.vmap(lambda pr, u, h: clip_inputs(p, jnp.where(h, u, cold_start(p, pr))))

    def solve(probs: RowProblem, u_init: Array, has_init: Array) -> DeviceResult:
        # full float32 products: a GPU's default (TF32) made the interior point fail 170 of the
        # 1,200 recorded QPs on an H200; on a CPU this changes nothing
        with jax.default_matmul_precision("highest"):
            return _solve(probs, u_init, has_init)

    def _solve(probs: RowProblem, u_init: Array, has_init: Array) -> DeviceResult:
        u0 = start(probs, u_init, has_init)
        if not p.unsafe_recovery:
            out = run(probs, u0)
        else:
            first, second, best = _two_passes(p, run, probs, u0)
            again = jax.vmap(lambda pr, a, b, c: recover(p, pr, a, b, c))(
                probs, first, second, best
            )
            unsafe = first[3] == UNSAFE
            out = jax.tree_util.tree_map(
                lambda a, b: jnp.where(unsafe.reshape((-1,) + (1,) * (a.ndim - 1)), b, a),
                first,
                again,
            )
        u, xs, cur, reason, its, nq = out
        finite = jnp.all(jnp.isfinite(u), axis=(1, 2))
        ok = ((reason == SOLVED) | (reason == LEAST_VIOLATION)) & finite
        return DeviceResult(u, xs, ok, reason.astype(jnp.int32), its, nq, cur)

    return solve
