"""The MPC's host side (method §6): the bridge's callback that solves the fired rows of a batch
with the SQP (`mpc.sqp`).

`HostSolver` is what the bridge's callback calls (`mpc.bridge`): it keeps each row's previous
plan and the step it was made at (`mpc.memory`, per shard of a sharded batch), solves the fired
rows in this process or, with `mpc.n_workers` other than 1 and at least two fired rows, in a pool
of worker processes (`mpc.pool`: at most one per core), one task per row, applies the fallback
rule (`mpc.rows`) and counts what happened (`stats`). Each row's QPs go to the backend of the
host's QP settings (`mpc.qp`; OSQP with the config's `osqp_*` fields by default). Processes, not
threads: OSQP releases the GIL only inside its QP solve, about half of a row's SQP; the
linearization and the line search in NumPy hold it, and threads solving rows side by side gain at
most 1.4x where processes gain 2-5x (benchmarks/README.md, `mpc_bridge`). A pool worker that dies
during a call, or runs past `mpc.worker_timeout_s`, costs its rows a fallback (reason
"worker_lost"), not the training: the pool is replaced before the next call. A pool that cannot
start because the main script lacks its `if __name__ == "__main__":` guard raises
`WorkerPoolError` (`mpc.pool.make_pool`).
"""

from __future__ import annotations

import os
import threading
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np

from mpcpearl_jax.envs.types import NavConfig
from mpcpearl_jax.mpc.config import MPCConfig
from mpcpearl_jax.mpc.memory import PlanMemory
from mpcpearl_jax.mpc.pool import (
    Stamped,
    broken,
    check_started,
    discard_pool,
    make_pool,
    pool_size,
    solve_stamped,
    stop_signals_blocked,
)
from mpcpearl_jax.mpc.problem import RowProblem, SolveResult, SolverParams, solver_params
from mpcpearl_jax.mpc.qp import QPSettings
from mpcpearl_jax.mpc.qp_osqp import OSQPSettings
from mpcpearl_jax.mpc.rows import NO_PLAN, STATUS_NAMES, row_outcome
from mpcpearl_jax.mpc.sqp import SQPSolver

WORKER_LOST = "worker_lost"  # the reason of a row whose pool worker died or hung

_WORKER_SOLVERS: dict[tuple[SolverParams, QPSettings], SQPSolver] = {}


def solve_in_worker(
    params: SolverParams, prob: RowProblem, u_init: np.ndarray | None, qp: QPSettings
) -> SolveResult:
    """One row in a pool worker: one cached solver per problem size and QP settings."""
    solver = _WORKER_SOLVERS.get((params, qp))
    if solver is None:
        solver = _WORKER_SOLVERS[params, qp] = SQPSolver(params, qp)
    return solver.solve(prob, u_init)


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

    qp: the settings of the rows' QP backend (`mpc.qp.QPSettings`); default OSQP with the
    config's `osqp_*` fields (`qp_osqp.OSQPSettings.from_config`).
    """

    # what a pool worker runs on one row (a test replaces it to kill or hang a worker)
    worker_solve = staticmethod(solve_in_worker)

    def __init__(self, nav: NavConfig, cfg: MPCConfig, qp: QPSettings | None = None):
        if not isinstance(cfg, MPCConfig):
            raise TypeError(f"cfg must be an MPCConfig, got {type(cfg).__name__}")
        self.nav = nav
        self.cfg = cfg
        self.qp = OSQPSettings.from_config(cfg) if qp is None else qp
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
            solver = self._solvers[params] = SQPSolver(params, self.qp)
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
        ok = [f in done and not broken(f) for f in futures]
        rows = [f.result() if good else None for f, good in zip(futures, ok, strict=True)]
        if not all(ok):
            self._drop_pool(check=any(f in done and broken(f) for f in futures))
        self._record_pool(t0, time.perf_counter(), [r for r in rows if r is not None])
        return [r.result if r is not None else _lost_result(params, lost) for r in rows]

    def _submit(self, params, probs, inits) -> list:
        def submit_all() -> list:
            if self._pool is None:
                self._pool = make_pool(self.n_workers)
            return [
                self._pool.submit(solve_stamped, self.worker_solve, params, p, u0, qp=self.qp)
                for p, u0 in zip(probs, inits, strict=True)
            ]

        with stop_signals_blocked():  # workers start here, blocked until pool_worker_init
            try:
                return submit_all()
            except BrokenProcessPool:  # a worker died between calls: no row was lost to it
                self._drop_pool(check=True)
                return submit_all()

    def _drop_pool(self, check: bool = False) -> None:
        """Discard the pool; with `check` (it broke), first raise where its workers could not
        start (`pool.check_started`)."""
        if self._pool is not None:
            pool, self._pool = self._pool, None
            try:
                if check:
                    check_started(pool, self.n_workers)
            finally:
                discard_pool(pool)

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
            mem.forget()

    def close(self) -> None:
        """Shut the worker pool down (if any); a later call starts a new one."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


def _lost_result(p: SolverParams, elapsed: float) -> SolveResult:
    """The result of a row whose worker was lost: not safe, so the row falls back."""
    u = np.zeros((p.horizon, 2))
    poses = np.zeros((p.horizon + 1, 3))
    return SolveResult(u, poses, False, WORKER_LOST, 0, 0, elapsed, float("nan"), WORKER_LOST)
