"""The MPC's host side (method §6): the SQP on OSQP and the bridge's callback that solves the
fired rows of a batch with it.

`SQPSolver` solves one row's problem (`mpc.problem`): the QP's sparsity pattern is built once per
problem size; each solve only updates values in place (and restarts OSQP's rho, so that no solver
state carries from one QP to the next), warm-starts from the shifted previous plan, bounds the
inputs by a trust region and accepts steps by a line search on the exact SAA merit (cost +
slack_penalty * violations).

`HostSolver` is what the bridge's callback calls (`mpc.bridge`): it keeps each row's previous
plan and the step it was made at (per shard of a sharded batch), solves the fired rows in this
process or, with `mpc.n_workers` other than 1 and at least two fired rows, in a pool of worker
processes (`pool_size`: at most one per core), one task per row, applies the fallback rule
(`mpc.rows`) and counts what happened (`stats`). Processes, not threads: OSQP releases the GIL
only inside its QP solve, about half of a row's SQP; the linearization and the line search in
NumPy hold it, and threads solving rows side by side gain at most 1.4x where processes gain 2-5x
(benchmarks/README.md, `mpc_bridge`). A pool worker that dies during a call, or runs past
`mpc.worker_timeout_s`, costs its rows a fallback (reason "worker_lost"), not the training: the
pool is replaced before the next call.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import threading
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from typing import Any, NamedTuple

import numpy as np
import osqp
import scipy.sparse as sp

from mpcpearl_jax.envs.types import NavConfig
from mpcpearl_jax.mpc import model
from mpcpearl_jax.mpc.config import MPCConfig
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
    solver_params,
    stage_weights,
    starts,
    violations,
)
from mpcpearl_jax.mpc.rows import NO_PLAN, STATUS_NAMES, row_outcome, shifted

# An unconverged QP still gives a search direction: the line search on the exact merit decides.
_OK_STATUS = (
    osqp.SolverStatus.OSQP_SOLVED,
    osqp.SolverStatus.OSQP_SOLVED_INACCURATE,
    osqp.SolverStatus.OSQP_MAX_ITER_REACHED,
)
WORKER_LOST = "worker_lost"  # the reason of a row whose pool worker died or hung


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


class SQPSolver:
    """SQP on OSQP with a fixed sparsity pattern, for problems of one size (K, M, N_adapt, S)."""

    def __init__(self, params: SolverParams):
        self.p = params
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
        values = qp_values(self.p, lin)
        lo, hi = qp_bounds(self.p, self.lay, lin, u)
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
    """One row in a pool worker: one cached solver per problem size."""
    solver = _WORKER_SOLVERS.get(params)
    if solver is None:
        solver = _WORKER_SOLVERS[params] = SQPSolver(params)
    return solver.solve(prob, u_init)


class Stamped(NamedTuple):
    """A pool task's row: its result, the worker's process id, and when the solve started and
    ended (`time.perf_counter`, a clock that all processes of a machine share)."""

    result: SolveResult
    worker: int
    start: float
    end: float


def solve_stamped(solve, params: SolverParams, prob: RowProblem, u_init) -> Stamped:
    """Entry point of a pool task: one row solved by `solve` (`HostSolver.worker_solve`)."""
    start = time.perf_counter()
    res = solve(params, prob, u_init)
    return Stamped(res, os.getpid(), start, time.perf_counter())


MAX_AUTO_WORKERS = 8  # `mpc.n_workers` 0: one worker per core, at most this many


def pool_size(n_workers: int, cores: int | None = None) -> int:
    """The worker processes of the MPC's pool for `mpc.n_workers` on `cores` cores (default:
    those this process may use): never more than the cores (a larger pool solves no faster
    and costs a process start and ~200 MB per worker); 0 takes one per core, at most
    `MAX_AUTO_WORKERS`. 1: no pool, the rows are solved in the calling process."""
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not Linux
            cores = os.cpu_count() or 1
    return min(n_workers, cores) if n_workers > 0 else min(cores, MAX_AUTO_WORKERS)


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
    workers with the stop signals blocked (`make_pool`), so one sent before this runs waits:
    SIGINT and SIGHUP are then ignored, and a SIGTERM sent to the old group is dropped."""
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

    def watch() -> None:
        while True:
            time.sleep(interval_s)
            if os.getppid() != parent_pid:
                os._exit(0)

    threading.Thread(target=watch, daemon=True, name="watch-parent").start()


def make_pool(n_workers: int) -> ProcessPoolExecutor:
    """The MPC's worker pool (spawned processes, `pool_worker_init`). multiprocessing's resource
    tracker, a helper process the pool's queues start, is started here with the stop signals
    blocked: it ignores SIGINT and SIGTERM itself, and a blocked SIGHUP never reaches it, so a
    closed terminal cannot kill it under the training (which then prints tracebacks)."""
    from multiprocessing import resource_tracker

    with stop_signals_blocked():  # ensure_running unblocks SIGINT and SIGTERM when it is done
        resource_tracker.ensure_running()
    with stop_signals_blocked():
        return ProcessPoolExecutor(
            n_workers,
            mp_context=get_context("spawn"),
            initializer=pool_worker_init,
            initargs=(os.getpid(),),
        )


@contextlib.contextmanager
def stop_signals_blocked():
    """Block the stop signals in this thread while the pool may start workers: a worker
    inherits the mask, so a Ctrl-C that comes before its initializer (`pool_worker_init`)
    cannot kill it; the training process gets the signal once it is unblocked."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def discard_pool(pool: ProcessPoolExecutor) -> None:
    """End a pool that lost a worker or hung: its workers are killed (a hung one would outlive
    `shutdown`), its queued rows cancelled; returns without waiting."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        with contextlib.suppress(Exception):
            proc.kill()
    pool.shutdown(wait=False, cancel_futures=True)


@dataclasses.dataclass
class PlanMemory:
    """Each row's previous plan, plans [B, K, 2] physical, and the step it was made at, plan_t
    [B] (`NO_PLAN`: none); episode: the stamp of the batch of episodes the plans belong to."""

    plans: np.ndarray
    plan_t: np.ndarray
    episode: tuple[int, ...] | None = None

    @classmethod
    def empty(cls, batch: int, horizon: int) -> PlanMemory:
        return cls(np.zeros((batch, horizon, 2)), np.full(batch, NO_PLAN, np.int64))

    def start(self, stamp: tuple[int, ...]) -> None:
        """A call's episode stamp (given flag, stamp...): a new batch of episodes forgets every
        plan; no stamp (flag 0) keeps them."""
        if stamp[0] and stamp != self.episode:
            self.plan_t[:] = NO_PLAN
            self.episode = stamp

    def warm(self, b: int, t: int) -> np.ndarray | None:
        """Row b's previous plan shifted by one step if it was made at t - 1, else None."""
        if self.plan_t[b] != t - 1:
            return None
        return shifted(self.plans[b])


def unpack_rows(layout: tuple, floats: np.ndarray, ints: np.ndarray) -> list[np.ndarray]:
    """The arrays `bridge.pack_rows` packed (NumPy views where the dtype is the packed one)."""
    out, at = [], {True: 0, False: 0}
    for is_float, shape, dtype in layout:
        src = floats if is_float else ints
        width = int(np.prod(shape, dtype=np.int64))
        part = src[:, at[is_float] : at[is_float] + width].reshape((src.shape[0], *shape))
        at[is_float] += width
        out.append(part.astype(dtype, copy=False))
    return out


class HostSolver:
    """The bridge's host side: `host(batch, idx, fired, pose, t, goal, static_lo, static_hi,
    static_radius, samples, valid, stamp, shard) -> (inputs [n, 2] float32, status [n] int32)`.

    The call's n rows are rows idx [n] of a batch (or shard) of `batch` rows; fired [n] bool marks
    those to solve (the others are padding, status `NOT_FIRED`). pose [n, 3], t [n], goal [n, 2],
    static_* [n, S, 2], [n, S, 2], [n, S]; samples [n, K, N_adapt, M, 2] and valid [n, N_adapt]
    (the GP prediction); stamp [3] uint32 (given flag and the episode stamp: `PlanMemory.start`);
    shard: which shard's plan memory to use (0 unsharded). inputs: the physical (v, delta) the
    row applies where its status is `SOLVED` or `FALLBACK_PLAN` (`mpc.rows`).
    """

    # what a pool worker runs on one row (a test replaces it to kill or hang a worker)
    worker_solve = staticmethod(solve_in_worker)

    def __init__(self, nav: NavConfig, cfg: MPCConfig):
        if not isinstance(cfg, MPCConfig):
            raise TypeError(f"cfg must be an MPCConfig, got {type(cfg).__name__}")
        self.nav = nav
        self.cfg = cfg
        self._solvers: dict[SolverParams, SQPSolver] = {}
        self._pool: ProcessPoolExecutor | None = None
        self._memory: dict[int, PlanMemory] = {}
        # the callbacks of the devices of one process may run in parallel threads
        self._lock = threading.Lock()
        self.reset_stats()

    def __call__(self, batch: int, *args: Any) -> tuple[np.ndarray, np.ndarray]:
        # operands read before taking the lock: a callback waiting for its operands while holding
        # it would stall the callbacks of the other devices, which share XLA's threads
        *rows, shard = [np.asarray(a) for a in args]
        with self._lock:
            return self._solve_call(self.memory(int(shard), batch), *rows)

    def packed_call(self, layout: tuple, batch: int, floats, ints, stamp, shard):
        """The call with its row operands packed by the bridge (`bridge.pack_rows`: idx, fired,
        pose, t, goal, static_lo, static_hi, static_radius, samples, valid)."""
        rows = unpack_rows(layout, np.asarray(floats), np.asarray(ints))
        return self(batch, *rows, stamp, shard)

    def memory(self, shard: int = 0, batch: int | None = None) -> PlanMemory:
        """The plan memory of a shard (0 unsharded), made (or remade, when the batch size
        changes) with `batch` rows."""
        mem = self._memory.get(shard)
        if batch is not None and (mem is None or mem.plans.shape[0] != batch):
            mem = self._memory[shard] = PlanMemory.empty(batch, self.cfg.horizon)
        if mem is None:
            raise KeyError(f"no plan memory for shard {shard}")
        return mem

    def _solve_call(self, mem, idx, fired, pose, t, goal, lo, hi, rad, samples, valid, stamp):
        t_start = time.perf_counter()
        mem.start(tuple(int(x) for x in np.asarray(stamp).ravel()))
        idx, t = np.asarray(idx, np.int64), np.asarray(t, np.int64)
        inputs = np.zeros((idx.shape[0], 2), np.float32)  # physical (v, delta) of MPC rows
        status = np.zeros(idx.shape[0], np.int32)
        sel = np.flatnonzero(np.asarray(fired, bool))
        f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
        probs = [
            RowProblem(
                f64(pose[j]),
                f64(goal[j]),
                f64(samples[j]),
                np.asarray(valid[j], bool),
                f64(lo[j]),
                f64(hi[j]),
                f64(rad[j]),
            )
            for j in sel
        ]
        inits = [mem.warm(idx[j], t[j]) for j in sel]
        results = self.solve_rows(probs, inits, lo.shape[1])
        for j, res in zip(sel, results, strict=True):
            status[j], u = self.merge_row(mem, idx[j], t[j], res)
            if u is not None:
                inputs[j] = u
        self._record(results, status[sel], time.perf_counter() - t_start)
        return inputs, status

    def merge_row(
        self, mem: PlanMemory, b: int, t: int, res: SolveResult
    ) -> tuple[int, np.ndarray | None]:
        """Row b's status and physical first input (v, delta), or None where the policy acts
        (`rows.row_outcome`); its memory holds the plan it applies from now on."""
        code, plan = row_outcome(res.ok, res.u, mem.warm(b, t))
        if plan is None:
            mem.plan_t[b] = NO_PLAN
            return code, None
        mem.plans[b], mem.plan_t[b] = plan, t
        return code, plan[0].copy()

    def solve_rows(
        self, probs: list[RowProblem], inits: list[np.ndarray | None], num_static: int
    ) -> list[SolveResult]:
        """The SQP on each problem from its start (the shifted previous plan, or None: cold), in
        the worker pool where `uses_pool`, else in this process."""
        params = solver_params(self.cfg, self.nav, num_static)
        if self.uses_pool(len(probs)):
            return self._solve_in_pool(params, probs, inits)
        return self.solve_here(params, probs, inits)

    @property
    def n_workers(self) -> int:
        """The pool's worker processes (`pool_size` of `mpc.n_workers`); 1: no pool."""
        return pool_size(self.cfg.n_workers)

    def uses_pool(self, n: int) -> bool:
        """Whether a call with n fired rows solves them in the worker pool: with more than one
        worker and at least two rows (one row is solved here: a pool task's round trip costs
        1-2 ms more, benchmarks/README.md, `mpc_bridge`)."""
        return n >= 2 and self.n_workers > 1

    def solve_here(self, params: SolverParams, probs, inits) -> list[SolveResult]:
        """The rows one after the other in this process."""
        solver = self._solvers.get(params)
        if solver is None:
            solver = self._solvers[params] = SQPSolver(params)
        return [solver.solve(p, u0) for p, u0 in zip(probs, inits, strict=True)]

    def start(self) -> None:
        """Start the worker pool now (where there is one and it is not running): its processes
        start and import beside whatever the caller does next (the bridge calls this when a
        rollout is traced, so they start during its compilation), and the first call finds
        them ready instead of waiting for them (seconds)."""
        if self.n_workers <= 1 or self._pool is not None:
            return
        with self._lock, stop_signals_blocked():
            if self._pool is None:
                self._pool = make_pool(self.n_workers)
                for _ in range(self.n_workers):  # the pool starts a process per waiting task
                    self._pool.submit(os.getpid)

    def _solve_in_pool(self, params, probs, inits) -> list[SolveResult]:
        """The rows on the worker pool, one task per row (a free worker takes the next row:
        solve times differ up to tenfold between rows, and fixed shares of the rows per worker
        lose more to the unequal shares than a task per row costs). A row whose worker died
        (the pool broke) or that is not done within `worker_timeout_s` gets a `WORKER_LOST`
        result, and the pool is replaced by a fresh one at the next call."""
        t0 = time.perf_counter()
        futures = self._submit(params, probs, inits)
        done, _ = wait(futures, timeout=self.cfg.worker_timeout_s)
        lost = time.perf_counter() - t0
        ok = [f in done and not _broken(f) for f in futures]
        rows = [f.result() if good else None for f, good in zip(futures, ok, strict=True)]
        if not all(ok):
            self._drop_pool()
        self._record_pool(t0, time.perf_counter(), [r for r in rows if r is not None])
        return [r.result if r is not None else _lost_result(params, lost) for r in rows]

    def _submit(self, params, probs, inits) -> list:
        def submit_all() -> list:
            if self._pool is None:
                self._pool = make_pool(self.n_workers)
            return [
                self._pool.submit(solve_stamped, self.worker_solve, params, p, u0)
                for p, u0 in zip(probs, inits, strict=True)
            ]

        with stop_signals_blocked():  # workers start here, blocked until pool_worker_init
            try:
                return submit_all()
            except BrokenProcessPool:  # a worker died between calls: no row was lost to it
                self._drop_pool()
                return submit_all()

    def _drop_pool(self) -> None:
        if self._pool is not None:
            discard_pool(self._pool)
            self._pool = None

    # ---------------------------------------------------------------- stats
    def _record_pool(self, t0: float, t1: float, rows: list[Stamped]) -> None:
        """A pool call's own cost, from the rows' stamps: of the worker that finished last, the
        time from the call's start (t0) to the start of its first row (pickling, queues, the
        worker waking up), and from the end of its last row to the results in hand (t1)."""
        if not rows:
            return
        last = max(rows, key=lambda r: r.end).worker
        mine = [r for r in rows if r.worker == last]
        self._stats["pool_send_s"].append(max(min(r.start for r in mine) - t0, 0.0))
        self._stats["pool_return_s"].append(max(t1 - max(r.end for r in mine), 0.0))

    def _record(self, results: list[SolveResult], status: np.ndarray, host_s: float) -> None:
        s = self._stats
        s["calls"] += 1
        s["rows_solved"] += len(results)
        s["host_call_s"].append(host_s)
        s["status"].update(STATUS_NAMES[int(c)] for c in status)
        s["reasons"].update(r.reason for r in results)
        ran = [r for r in results if r.reason != WORKER_LOST]  # rows whose SQP ran
        s["sqp_stops"].update(r.stop for r in ran)
        s["starts"].update(r.start for r in ran)
        s["solve_s"].extend(r.solve_time for r in ran)
        s["qp_iters"].extend(r.qp_iters for r in ran)
        s["n_qp"].extend(r.n_qp for r in ran)

    def stats(self) -> dict[str, Any]:
        """Counters since the last reset: calls (host callbacks), rows_solved (fired rows handed
        to the host), fallbacks, status and reason counts, how each row's SQP ended (sqp_stops)
        and which start its plan came from (starts), per-row solve times (s), QP iterations and
        QPs per row, host time per call (s), and per call solved in the pool, of the worker that
        finished last, the time until its first row started and from its last row's end to the
        results in hand (pool_send_s, pool_return_s: `_record_pool`). A row whose pool worker
        was lost counts in rows_solved, status, reasons ("worker_lost") and fallbacks only."""
        s = self._stats
        out = {
            k: (dict(v) if isinstance(v, Counter) else (list(v) if isinstance(v, list) else v))
            for k, v in s.items()
        }
        out["fallbacks"] = s["status"]["fallback_plan"] + s["status"]["fallback_policy"]
        return out

    def reset_stats(self) -> None:
        self._stats: dict[str, Any] = {
            "calls": 0,
            "rows_solved": 0,
            "status": Counter(),
            "reasons": Counter(),
            "sqp_stops": Counter(),  # why each row's SQP ended (problem.SQP_STOPS)
            "starts": Counter(),  # the start each row's plan came from (problem.START_NAMES)
            "solve_s": [],
            "qp_iters": [],
            "n_qp": [],
            "host_call_s": [],
            "pool_send_s": [],
            "pool_return_s": [],
        }

    def reset_memory(self) -> None:
        """Forget every row's previous plan (the next solves start cold)."""
        for mem in self._memory.values():
            mem.plan_t[:] = NO_PLAN

    def close(self) -> None:
        """Shut the worker pool down (if any); a later call starts a new one."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


def _broken(future) -> bool:
    """Whether a finished row's worker was lost (the pool broke under it)."""
    return isinstance(future.exception(), BrokenProcessPool)


def _lost_result(p: SolverParams, elapsed: float) -> SolveResult:
    """The result of a row whose worker was lost: not safe, so the row falls back."""
    u = np.zeros((p.horizon, 2))
    poses = np.zeros((p.horizon + 1, 3))
    return SolveResult(u, poses, False, WORKER_LOST, 0, 0, elapsed, float("nan"), WORKER_LOST)
