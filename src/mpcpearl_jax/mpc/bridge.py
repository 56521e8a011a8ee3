"""The bridge from jitted rollouts to the host MPC (method §6).

One batch-level `lax.cond(jnp.any(fire))` guards the GP prediction (JAX) and a single
`jax.pure_callback` that receives the whole env batch plus the fire mask; the host solves only the
fired rows. Usable inside `jit` and a `lax.scan` over time with a flat batch B (seeds x tasks x
envs folded into one axis; an outer vmap would batch the predicate and is refused).

Per-row memory on the host (previous plan and the step it was made at) gives warm starts: a row
whose t is the previous t + 1 starts from the shifted plan, otherwise from a cold start. Callers
that run the bridge over several batches of episodes pass an `episode` stamp (the collector does):
a call with a new stamp forgets every plan first, so no plan outlives its episodes and a row's
actions depend only on its own episode (exact resume of training).

With the batch sharded over a device mesh (`on_mesh`), the guard and the callback run per shard
inside a `shard_map`: each device calls its own process's host for its own fired rows only, with
plan memory and stamp kept per shard (docs/distributed.md).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from mpcpearl_jax.envs.dynamics import to_normalized
from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.types import EnvState, TaskParams
from mpcpearl_jax.mpc import device_bridge as db
from mpcpearl_jax.mpc.config import MPCConfig
from mpcpearl_jax.mpc.device_solver import REASONS, make_batch_solver
from mpcpearl_jax.mpc.gp import predict_row
from mpcpearl_jax.mpc.solver import (
    STOP_SIGNALS,
    RowProblem,
    SolveResult,
    SQPSolver,
    pool_worker_init,
    solve_in_worker,
    solver_params,
)

# per-row status codes returned by the bridge
NOT_FIRED = 0
SOLVED = 1  # the MPC action of a safe solve
FALLBACK_PLAN = 2  # solve failed or unsafe: the previous plan shifted by one step
FALLBACK_POLICY = 3  # solve failed or unsafe and no previous plan: the policy action
STATUS_NAMES = {
    NOT_FIRED: "not_fired",
    SOLVED: "solved",
    FALLBACK_PLAN: "fallback_plan",
    FALLBACK_POLICY: "fallback_policy",
}


_SHARD_CALLBACK: Any = None


def make_pool(n_workers: int) -> ProcessPoolExecutor:
    """The MPC's worker pool (spawned processes, `pool_worker_init`). multiprocessing's resource
    tracker, a helper process the pool's queues start, is started here with the stop signals
    blocked: it ignores SIGINT and SIGTERM itself, and a blocked SIGHUP never reaches it, so a
    closed terminal cannot kill it under the training (which then prints tracebacks)."""
    from multiprocessing import resource_tracker

    with _stop_signals_blocked():  # ensure_running unblocks SIGINT and SIGTERM when it is done
        resource_tracker.ensure_running()
    with _stop_signals_blocked():
        return ProcessPoolExecutor(
            n_workers,
            mp_context=get_context("spawn"),
            initializer=pool_worker_init,
            initargs=(os.getpid(),),
        )


@contextlib.contextmanager
def _stop_signals_blocked():
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


def _shard_callback(fn, out_shapes, *args):
    """`jax.pure_callback(fn, out_shapes, *args)` for the body of a `shard_map`, where each
    device calls `fn` with its own operands. `jax.pure_callback` first copies its operands onto
    the first CPU device, and with several CPU devices that copy waits behind the program they
    all run, which waits for the callbacks: a deadlock. This primitive hands `fn` the operands
    as XLA passes them (NumPy arrays), through the same lowering as `jax.pure_callback`."""
    global _SHARD_CALLBACK
    if _SHARD_CALLBACK is None:
        from jax._src import callback as jcb
        from jax._src import core
        from jax.interpreters import mlir

        prim = core.Primitive("mpc_shard_callback")
        prim.multiple_results = True
        prim.def_abstract_eval(lambda *avals, fn, result_avals: list(result_avals))

        def lowering(ctx, *operands, fn, result_avals):
            axis_context = ctx.module_context.axis_context
            sharding = jcb._callback_op_sharding(axis_context, None, ctx.avals_out)
            out, _, _ = jcb.emit_python_callback(
                ctx,
                lambda *a: tuple(np.asarray(x) for x in fn(*a)),
                None,
                list(operands),
                ctx.avals_in,
                ctx.avals_out,
                has_side_effect=False,
                returns_token=False,
                sharding=sharding,
            )
            return out

        mlir.register_lowering(prim, lowering, cacheable=False)
        _SHARD_CALLBACK = prim
    from jax._src import core

    avals = tuple(core.ShapedArray(s.shape, s.dtype) for s in out_shapes)
    return tuple(_SHARD_CALLBACK.bind(*args, fn=fn, result_avals=avals))


class MPCBridge:
    """`bridge(key, fire, states, params, policy_actions, episode=None) -> (actions, used_mpc,
    status)`.

    fire [B] bool; states EnvState with pose [B, 3], t [B]; params TaskParams batched [B];
    policy_actions [B, 2] normalized; episode: optional uint32 [2] stamp of the batch of episodes
    (a new stamp resets the per-row plan memory, see module doc). Returns actions [B, 2]
    normalized (the MPC action on fired rows with a safe solve, else the fallback), used_mpc [B]
    bool (fired and solved), status [B] int32 (codes above). `stats()` / `reset_stats()` expose
    host-side counters.
    """

    def __init__(self, env: NavEnv, cfg: MPCConfig):
        if not isinstance(cfg, MPCConfig):
            raise TypeError(f"cfg must be an MPCConfig, got {type(cfg).__name__}")
        self.env = env
        self.cfg = cfg
        self._solvers: dict[Any, SQPSolver] = {}
        self._pool: ProcessPoolExecutor | None = None
        self._plans = np.zeros((0, cfg.horizon, 2))
        self._plan_t = np.zeros(0, np.int64)
        self._episode: tuple[int, ...] | None = None
        # per-shard plan memory (plans, plan_t, episode) when sharded; the callbacks of the
        # devices of one process may run in parallel threads, so the host side takes a lock
        self._shards: dict[int, tuple[np.ndarray, np.ndarray, tuple[int, ...] | None]] = {}
        self._lock = threading.Lock()
        self._device_solvers: dict[int, Any] = {}
        self.reset_stats()

    # ---------------------------------------------------------------- JAX side
    def __call__(
        self,
        key: Array,
        fire: Array,
        states: EnvState,
        params: TaskParams,
        policy_actions: Array,
        episode: Array | None = None,
    ) -> tuple[Array, Array, Array]:
        return self._call(key, fire, states, params, policy_actions, self._stamp(episode))

    def on_mesh(self, mesh) -> Any:
        """The bridge for a flat batch whose leading axis is split over the one-axis `mesh`
        (`mpcpearl_jax.distributed`): the same signature and per-row results, with one guard and
        one host callback per shard, in the process that holds it. Returns self without a mesh."""
        if mesh is None or self.on_device:  # the device path is plain JAX: sharded as its inputs
            return self
        from jax.sharding import PartitionSpec as P

        axis = mesh.axis_names[0]

        def local(key, fire, states, params, policy_actions, stamp):
            shard = jax.lax.axis_index(axis)
            row0 = shard * fire.shape[0]
            return self._call(key, fire, states, params, policy_actions, stamp, shard, row0)

        rows, whole = P(axis), P()
        # the callback's outputs are per shard, which the varying-axes check cannot see
        mapped = jax.shard_map(
            local,
            mesh=mesh,
            in_specs=(whole, rows, rows, rows, rows, whole),
            out_specs=(rows, rows, rows),
            check_vma=False,
        )
        return lambda key, fire, states, params, policy_actions, episode=None: mapped(
            key, fire, states, params, policy_actions, self._stamp(episode)
        )

    @staticmethod
    def _stamp(episode: Array | None) -> Array:
        # [given, stamp...]: 0 = no stamp (the memory is never reset by a call)
        if episode is None:
            return jnp.zeros((3,), jnp.uint32)
        stamp = jnp.concatenate([jnp.ones((1,), jnp.uint32), jnp.ravel(episode)[:2]])
        return stamp.astype(jnp.uint32)

    def _call(self, key, fire, states, params, policy_actions, stamp, shard=None, row0=None):
        """The guarded callback on a batch (or, with shard/row0, one shard of it: row0 is the
        global index of its first row, which keys the GP samples)."""
        batch = fire.shape[0]
        shard = jnp.zeros((), jnp.int32) if shard is None else jnp.asarray(shard, jnp.int32)
        out_shapes = (
            jax.ShapeDtypeStruct((batch, 2), jnp.float32),
            jax.ShapeDtypeStruct((batch,), jnp.bool_),
            jax.ShapeDtypeStruct((batch,), jnp.int32),
        )

        def solve(_):
            samples, valid = self.predict_fired(key, fire, states, params, row0)
            call = jax.pure_callback if row0 is None else _shard_callback
            return call(
                self._host,
                out_shapes,
                fire,
                states.pose,
                states.t,
                params.goal,
                params.static_lo,
                params.static_hi,
                params.static_radius,
                samples,
                valid,
                stamp,
                shard,
            )

        def skip(_):
            return (
                jnp.zeros((batch, 2), jnp.float32),
                jnp.zeros(batch, bool),
                jnp.zeros(batch, jnp.int32),
            )

        # the host returns physical inputs (v, delta) of the MPC's rows; the env's action
        # mapping turns them into normalized actions, the other rows keep the policy's action
        u, used, status = jax.lax.cond(jnp.any(fire), solve, skip, None)
        has_mpc = (status == SOLVED) | (status == FALLBACK_PLAN)
        mpc_actions = to_normalized(u, self.env.config.v_max)
        actions = jnp.where(has_mpc[:, None], mpc_actions, policy_actions.astype(jnp.float32))
        return actions, used, status

    def predict_fired(
        self, key: Array, fire: Array, states: EnvState, params: TaskParams, row0: Any = None
    ) -> tuple[Array, Array]:
        """GP samples [B, K, N_adapt, M, 2] and valid [B, N_adapt], computed for fired rows only.

        Up to `cap` fired rows are gathered into a small batch (static size), predicted and
        scattered back (other rows hold zeros, which the host never reads); if more rows fire,
        every row is predicted. row0: global index of the first row (a shard of a larger batch).
        """
        batch = fire.shape[0]
        every = None if row0 is None else row0 + jnp.arange(batch)
        cap = min(batch, max(16, -(-batch // 4)))
        if cap == batch:
            return self.predict(key, states, params, every)

        def compact(_):
            idx = jnp.nonzero(fire, size=cap, fill_value=batch)[0]  # [cap], batch = padding
            take = lambda x: jnp.take(x, idx, axis=0, mode="clip")  # noqa: E731
            sub_s = jax.tree_util.tree_map(take, states)
            sub_p = jax.tree_util.tree_map(take, params)
            samples, valid = self.predict(key, sub_s, sub_p, idx if row0 is None else row0 + idx)
            put = lambda full, part: full.at[idx].set(part, mode="drop")  # noqa: E731
            full_samples = jnp.zeros((batch, *samples.shape[1:]), samples.dtype)
            full_valid = jnp.zeros((batch, *valid.shape[1:]), valid.dtype)
            return put(full_samples, samples), put(full_valid, valid)

        return jax.lax.cond(
            jnp.sum(fire) <= cap, compact, lambda _: self.predict(key, states, params, every), None
        )

    def predict(
        self, key: Array, states: EnvState, params: TaskParams, rows: Array | None = None
    ) -> tuple[Array, Array]:
        """GP samples for every row: [B, K, N_adapt, M, 2] and valid [B, N_adapt].

        Row b samples with fold_in(key, rows[b]) (rows defaults to arange(B)), so a row's samples
        do not depend on which other rows are predicted with it.
        """
        if rows is None:
            rows = jnp.arange(states.t.shape[0])
        keys = jax.vmap(lambda r: jax.random.fold_in(key, r))(rows)
        row = lambda k, pose, t, hp, hm: predict_row(k, pose, t, hp, hm, self.cfg)  # noqa: E731
        return jax.vmap(row)(keys, states.pose, states.t, params.human_pos, params.human_mask)

    # ---------------------------------------------------------------- device side
    @property
    def on_device(self) -> bool:
        """Whether the SQP runs on the device (`mpc.solver = "device"`): callers then carry a
        `DeviceMemory` through `step` instead of calling the bridge."""
        return self.cfg.solver == "device"

    def init_memory(self, batch: int) -> db.DeviceMemory:
        """The device path's per-row memory at the start of a batch of episodes (no plans)."""
        return db.init_memory(batch, self.cfg.horizon)

    def step(
        self,
        memory: db.DeviceMemory,
        key: Array,
        fire: Array,
        states: EnvState,
        params: TaskParams,
        policy_actions: Array,
    ) -> tuple[db.DeviceMemory, Array, Array, Array]:
        """The bridge on the device (`on_device`): `(memory, actions, used_mpc, status)` with the
        same meaning, fallbacks and status codes as `__call__`, the GP prediction and the SQP
        (`device_solver`) inside the jitted step. Hand the final memory's counts to
        `record_counts` (e.g. by one `jax.debug.callback` after the scan)."""
        batch = fire.shape[0]
        solve = self._device_solver(params.static_lo.shape[1])
        every = jnp.arange(batch)

        def run(_):
            samples, valid = self.predict_fired(key, fire, states, params)
            rows = lambda idx: db.solve_rows(solve, memory, idx, states, params, samples, valid)  # noqa: E731
            cap = min(batch, max(16, -(-batch // 4)))
            if cap == batch:
                return rows(every)

            def some(_):
                idx = jnp.nonzero(fire, size=cap, fill_value=batch)[0]
                return db.scatter(batch, idx, rows(idx))

            return jax.lax.cond(jnp.sum(fire) <= cap, some, lambda _: rows(every), None)

        shapes = jax.eval_shape(run, None)
        skip = lambda _: jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)  # noqa: E731
        res = jax.lax.cond(jnp.any(fire), run, skip, None)
        plans, plan_t, status, u0 = db.merge(memory, fire, states.t, res)
        memory = db.DeviceMemory(plans, plan_t, memory.counts + db.count(fire, status, res))
        has_mpc = (status == SOLVED) | (status == FALLBACK_PLAN)
        mpc_actions = to_normalized(u0, self.env.config.v_max)
        actions = jnp.where(has_mpc[:, None], mpc_actions, policy_actions.astype(jnp.float32))
        return memory, actions, status == SOLVED, status

    def _device_solver(self, num_static: int):
        solve = self._device_solvers.get(num_static)
        if solve is None:
            params = solver_params(self.cfg, self.env.config, num_static)
            solve = make_batch_solver(params, self.cfg.device_qp_iters)
            self._device_solvers[num_static] = solve
        return solve

    def record_counts(self, counts) -> None:
        """Add a device path's counters (`DeviceMemory.counts`) to `stats()` (host side)."""
        c = dict(zip(db.COUNT_NAMES, (int(x) for x in np.asarray(counts)), strict=True))
        with self._lock:
            s = self._stats
            s["calls"] += c["calls"]
            s["rows_solved"] += c["rows"]
            s["status"].update({STATUS_NAMES[i]: c[f"status{i}"] for i in range(1, 4)})
            s["reasons"].update({r: c[r] for r in REASONS if c[r]})
            s["qp_iters_total"] += c["qp_iters"]
            s["n_qp_total"] += c["n_qp"]

    # ---------------------------------------------------------------- host side
    def _host(self, *args):
        # operands read before taking the lock: a callback waiting for its operands while holding
        # it would stall the callbacks of the other devices, which share XLA's threads
        *rows, shard = [np.asarray(a) for a in args]
        with self._lock:
            shard = int(shard)  # 0 unless sharded: each shard its own plan memory
            none = (np.zeros((0, self.cfg.horizon, 2)), np.zeros(0, np.int64), None)
            self._plans, self._plan_t, self._episode = self._shards.get(shard, none)
            try:
                return self._host_rows(*rows)
            finally:
                self._shards[shard] = (self._plans, self._plan_t, self._episode)

    def _host_rows(self, fire, pose, t, goal, lo, hi, rad, samples, valid, stamp):
        t_start = time.perf_counter()
        fire, t = np.asarray(fire, bool), np.asarray(t, np.int64)
        self._resize(fire.shape[0])
        stamp = tuple(int(x) for x in np.asarray(stamp).ravel())
        if stamp[0] and stamp != self._episode:  # a new batch of episodes: forget old plans
            self._plan_t[:] = -10  # (of these rows only: another shard keeps its own)
            self._episode = stamp
        inputs = np.zeros((fire.shape[0], 2), np.float32)  # physical (v, delta) of MPC rows
        status = np.zeros(fire.shape[0], np.int32)
        rows = np.flatnonzero(fire)
        f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
        probs = [
            RowProblem(
                f64(pose[b]),
                f64(goal[b]),
                f64(samples[b]),
                np.asarray(valid[b], bool),
                f64(lo[b]),
                f64(hi[b]),
                f64(rad[b]),
            )
            for b in rows
        ]
        inits = [self._warm_plan(b, t[b]) for b in rows]
        results = self._solve_rows(probs, inits, lo.shape[1])
        for b, res in zip(rows, results, strict=True):
            status[b], u = self._merge_row(b, t[b], res)
            if u is not None:
                inputs[b] = u
        self._record(results, status[rows], time.perf_counter() - t_start)
        return inputs, status == SOLVED, status

    def _resize(self, batch: int) -> None:
        if self._plans.shape[0] != batch:
            self._plans = np.zeros((batch, self.cfg.horizon, 2))
            self._plan_t = np.full(batch, -10, np.int64)

    def _warm_plan(self, b: int, t: int) -> np.ndarray | None:
        """The row's previous plan shifted by one step if it was made at t - 1, else None."""
        if self._plan_t[b] != t - 1:
            return None
        return np.concatenate([self._plans[b, 1:], self._plans[b, -1:]], axis=0)

    def _merge_row(self, b: int, t: int, res: SolveResult) -> tuple[int, np.ndarray | None]:
        """Update the row's memory; return (status, physical first input (v, delta), or None
        where the policy acts)."""
        if res.ok:
            self._plans[b], self._plan_t[b] = res.u, t
            return SOLVED, res.u[0].copy()
        shifted = self._warm_plan(b, t)
        if shifted is not None:  # method §6 fallback: the previous plan shifted by one step
            self._plans[b], self._plan_t[b] = shifted, t
            return FALLBACK_PLAN, shifted[0].copy()
        self._plan_t[b] = -10
        return FALLBACK_POLICY, None

    def _solve_rows(self, probs, inits, num_static: int) -> list[SolveResult]:
        params = solver_params(self.cfg, self.env.config, num_static)
        if self.cfg.n_workers > 1 and len(probs) > 1:
            if self._pool is None:
                self._pool = make_pool(self.cfg.n_workers)
            with _stop_signals_blocked():  # workers start here, blocked until pool_worker_init
                results = self._pool.map(solve_in_worker, [params] * len(probs), probs, inits)
            return list(results)
        solver = self._solvers.get(params)
        if solver is None:
            solver = self._solvers[params] = SQPSolver(params)
        return [solver.solve(p, u0) for p, u0 in zip(probs, inits, strict=True)]

    # ---------------------------------------------------------------- stats
    def _record(self, results: list[SolveResult], status: np.ndarray, host_s: float) -> None:
        s = self._stats
        s["calls"] += 1
        s["rows_solved"] += len(results)
        s["host_call_s"].append(host_s)
        s["status"].update(STATUS_NAMES[int(c)] for c in status)
        s["reasons"].update(r.reason for r in results)
        s["sqp_stops"].update(r.stop for r in results)
        s["starts"].update(r.start for r in results)
        s["solve_s"].extend(r.solve_time for r in results)
        s["qp_iters"].extend(r.qp_iters for r in results)
        s["n_qp"].extend(r.n_qp for r in results)

    def stats(self) -> dict[str, Any]:
        """Counters since the last reset: calls (host callbacks), rows_solved, fallbacks, status
        and reason counts, how each row's SQP ended (sqp_stops) and which start its plan came
        from (starts), per-row solve times (s), QP iterations and QPs per row, host time per
        call (s)."""
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
            "sqp_stops": Counter(),  # why each row's SQP ended (solver.SQP_STOPS)
            "starts": Counter(),  # the start each row's plan came from (solver.START_NAMES)
            "solve_s": [],
            "qp_iters": [],
            "n_qp": [],
            "host_call_s": [],
            # the device path's totals (it keeps no per-row lists)
            "qp_iters_total": 0,
            "n_qp_total": 0,
        }

    def reset_memory(self) -> None:
        """Forget every row's previous plan (the next solves start cold)."""
        self._plan_t[:] = -10
        for _, plan_t, _ in self._shards.values():
            plan_t[:] = -10

    def close(self) -> None:
        """Shut the worker pool down (if any)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


def make_mpc_bridge(env: NavEnv, cfg: MPCConfig | None = None) -> MPCBridge:
    """The MPC bridge of method §6 for an env (see `MPCBridge`)."""
    return MPCBridge(env, cfg or MPCConfig())
