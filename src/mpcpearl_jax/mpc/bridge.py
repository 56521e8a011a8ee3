"""The bridge from jitted rollouts to the host MPC (method §6).

A rollout drives the bridge through one interface, inside `jit` and a `lax.scan` over time:

    carry = bridge.init(batch, episode)            # before the scan
    carry, actions, used_mpc, status = bridge.step(carry, key, fire, states, params, policy_actions)
    bridge.finish(carry)                           # after the scan

with a flat batch B (seeds x tasks x envs folded into one axis; an outer vmap would batch the
guard below and is refused). Each step, one batch-level `lax.cond(jnp.any(fire))` guards the GP
prediction (JAX) and a single `jax.pure_callback` to the host solver (`mpc.host`). Only the fired
rows travel: up to a static cap (`fired_cap`) they are gathered on the device, predicted, sent
with their row indices (packed into one float and one int array: `pack_rows`), and their results
scattered back; where more rows fire, the whole batch is sent with the fire mask.

Per-row memory on the host (previous plan and the step it was made at) gives warm starts: a row
whose t is the previous t + 1 starts from the shifted plan, otherwise from a cold start. The carry
is the stamp of the batch of episodes (`init`'s `episode`; the collector gives one): a call with a
new stamp forgets every plan first, so no plan outlives its episodes and a row's actions depend
only on its own episode (exact resume of training).

With the batch sharded over a device mesh (`on_mesh`), the guard and the callback run per shard
inside a `shard_map`: each device calls its own process's host for its own fired rows only, with
plan memory kept per shard (docs/distributed.md).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.types import EnvState, TaskParams
from mpcpearl_jax.mpc.config import MPCConfig
from mpcpearl_jax.mpc.gp import predict_row
from mpcpearl_jax.mpc.host import HostSolver
from mpcpearl_jax.mpc.rows import SOLVED, merge_actions

_SHARD_CALLBACK: Any = None


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


def pack_rows(arrays: Sequence[Array]) -> tuple[Array, Array, tuple]:
    """Arrays with a leading row axis [n, ...] packed into (floats [n, F], ints [n, I], layout):
    the float arrays side by side in their common dtype, the others (ints, bools) in a common
    int dtype; `host.unpack_rows(layout, floats, ints)` gives back each array, in order, with
    its values and dtype."""
    n = arrays[0].shape[0]
    is_float = [jnp.issubdtype(a.dtype, jnp.floating) for a in arrays]
    f_dtype = jnp.result_type(*(a for a, f in zip(arrays, is_float, strict=True) if f))
    i_dtype = jnp.result_type(
        *(a for a, f in zip(arrays, is_float, strict=True) if not f), jnp.int32
    )

    def side_by_side(flag, dtype):
        parts = [
            jnp.reshape(a, (n, -1)).astype(dtype)
            for a, f in zip(arrays, is_float, strict=True)
            if f == flag
        ]
        return jnp.concatenate(parts, axis=1)

    layout = tuple(
        (f, a.shape[1:], np.dtype(a.dtype).str) for a, f in zip(arrays, is_float, strict=True)
    )
    return side_by_side(True, f_dtype), side_by_side(False, i_dtype), layout


def fired_cap(batch: int) -> int:
    """How many fired rows of a batch are gathered and sent alone (static); beyond it the whole
    batch is sent."""
    return min(batch, max(16, -(-batch // 4)))


class Bridge(Protocol):
    """What a rollout calls (module doc); `MPCBridge` and its sharded form fill it. The carry is
    a pytree of the implementation's own (`MPCBridge`'s: the episode stamp)."""

    def init(self, batch: int, episode: Array | None = None) -> Any: ...

    def step(
        self,
        carry: Any,
        key: Array,
        fire: Array,
        states: EnvState,
        params: TaskParams,
        policy_actions: Array,
    ) -> tuple[Any, Array, Array, Array]: ...

    def finish(self, carry: Any) -> None: ...

    def stats(self) -> dict[str, Any]: ...

    def reset_stats(self) -> None: ...

    def reset_memory(self) -> None: ...

    def close(self) -> None: ...


class MPCBridge:
    """The MPC of method §6 on a flat batch of B rows (module doc).

    `init(batch, episode=None) -> carry`: episode, an optional uint32 [2] stamp of the batch of
    episodes (a new stamp resets the per-row plan memory). `step(carry, key, fire, states, params,
    policy_actions) -> (carry, actions, used_mpc, status)`: fire [B] bool; states EnvState with
    pose [B, 3], t [B]; params TaskParams batched [B]; policy_actions [B, 2] normalized. actions
    [B, 2] normalized (the MPC action on fired rows with a safe solve, else the fallback of
    `mpc.rows`), used_mpc [B] bool (fired and solved), status [B] int32 (`mpc.rows` codes).
    `finish(carry)` after the last step. `stats()` / `reset_stats()` expose the host's counters.
    `host`: the host side (default `HostSolver(env.config, cfg)`).
    """

    def __init__(self, env: NavEnv, cfg: MPCConfig, host: HostSolver | None = None):
        if not isinstance(cfg, MPCConfig):
            raise TypeError(f"cfg must be an MPCConfig, got {type(cfg).__name__}")
        self.env = env
        self.cfg = cfg
        self.host = HostSolver(env.config, cfg) if host is None else host

    # ---------------------------------------------------------------- the interface
    def init(self, batch: int, episode: Array | None = None) -> Array:
        """The carry of a batch of `batch` rows: the stamp [3] uint32 (given flag, episode).
        Also starts the host's worker pool (`HostSolver.start`): called where a rollout is
        traced, its processes start while the rollout compiles."""
        start = getattr(self.host, "start", None)
        if start is not None:
            start()
        if episode is None:  # no stamp: the memory is never reset by a call
            return jnp.zeros((3,), jnp.uint32)
        stamp = jnp.concatenate([jnp.ones((1,), jnp.uint32), jnp.ravel(episode)[:2]])
        return stamp.astype(jnp.uint32)

    def step(
        self,
        carry: Array,
        key: Array,
        fire: Array,
        states: EnvState,
        params: TaskParams,
        policy_actions: Array,
    ) -> tuple[Array, Array, Array, Array]:
        actions, used, status = self.local_step(carry, key, fire, states, params, policy_actions)
        return carry, actions, used, status

    def finish(self, carry: Array) -> None:
        """After a batch of episodes: nothing is left to do (each host call keeps its counters)."""
        return None

    def on_mesh(self, mesh) -> MPCBridge | ShardedBridge:
        """The bridge for a flat batch whose leading axis is split over the one-axis `mesh`
        (`mpcpearl_jax.distributed`): the same interface and per-row results, with one guard and
        one host callback per shard, in the process that holds it. Returns self without a mesh."""
        return self if mesh is None else ShardedBridge(self, mesh)

    # ---------------------------------------------------------------- JAX side
    def local_step(self, stamp, key, fire, states, params, policy_actions, shard=None, row0=None):
        """(actions, used_mpc, status) of a batch (or, with shard/row0, of one shard of it: row0
        is the global index of its first row, which keys the GP samples)."""
        batch = fire.shape[0]
        shard = jnp.zeros((), jnp.int32) if shard is None else jnp.asarray(shard, jnp.int32)

        def solve(_):
            return self._solve_fired(key, fire, states, params, stamp, shard, row0)

        def skip(_):
            return jnp.zeros((batch, 2), jnp.float32), jnp.zeros(batch, jnp.int32)

        # the host returns physical inputs (v, delta) of the MPC's rows (`mpc.rows`)
        u, status = jax.lax.cond(jnp.any(fire), solve, skip, None)
        actions = merge_actions(u, status, policy_actions, self.env.config.v_max)
        return actions, status == SOLVED, status

    def _solve_fired(self, key, fire, states, params, stamp, shard, row0):
        """u [B, 2] and status [B] from one host call on the fired rows: gathered up to
        `fired_cap`, the whole batch with the fire mask beyond it."""
        batch = fire.shape[0]
        call = jax.pure_callback if row0 is None else _shard_callback

        def on_rows(idx, fired):  # rows idx [n] of the batch, those to solve fired [n]
            take = lambda x: jnp.take(x, idx, axis=0, mode="clip")  # noqa: E731
            sub_s = jax.tree_util.tree_map(take, states)
            sub_p = jax.tree_util.tree_map(take, params)
            samples, valid = self.predict(key, sub_s, sub_p, idx if row0 is None else row0 + idx)
            n = idx.shape[0]
            shapes = (
                jax.ShapeDtypeStruct((n, 2), jnp.float32),
                jax.ShapeDtypeStruct((n,), jnp.int32),
            )
            # the host call's operands (`HostSolver`) packed into one float and one int array:
            # each operand is its own copy from the device (benchmarks/README.md, `mpc_bridge`)
            floats, ints, layout = pack_rows(
                (idx, fired, sub_s.pose, sub_s.t, sub_p.goal, sub_p.static_lo, sub_p.static_hi)
                + (sub_p.static_radius, samples, valid)
            )
            host = functools.partial(self.host.packed_call, layout, batch)
            u, status = call(host, shapes, floats, ints, stamp, shard)

            def put(part):  # back to the batch's rows (the padding, idx = batch, is dropped)
                full = jnp.zeros((batch, *part.shape[1:]), part.dtype)
                return full.at[idx].set(part, mode="drop")

            return put(u), put(status)

        every = jnp.arange(batch, dtype=jnp.int32)
        cap = fired_cap(batch)
        if cap == batch:
            return on_rows(every, fire)

        def some(_):
            idx = jnp.nonzero(fire, size=cap, fill_value=batch)[0]  # [cap], batch = padding
            return on_rows(idx, idx < batch)

        return jax.lax.cond(jnp.sum(fire) <= cap, some, lambda _: on_rows(every, fire), None)

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

    # ---------------------------------------------------------------- host side
    def stats(self) -> dict[str, Any]:
        """The host's counters since the last reset (`HostSolver.stats`)."""
        return self.host.stats()

    def reset_stats(self) -> None:
        self.host.reset_stats()

    def reset_memory(self) -> None:
        """Forget every row's previous plan (the next solves start cold)."""
        self.host.reset_memory()

    def close(self) -> None:
        """Shut the host's worker pool down (if any); a later call starts it again."""
        self.host.close()


class ShardedBridge:
    """`MPCBridge.on_mesh`: the bridge's interface over a batch split along the one axis of
    `mesh`; each shard's guard, GP prediction and host call run on its own device."""

    def __init__(self, bridge: MPCBridge, mesh):
        from jax.sharding import PartitionSpec as P

        self.bridge = bridge
        axis = mesh.axis_names[0]

        def local(stamp, key, fire, states, params, policy_actions):
            shard = jax.lax.axis_index(axis)
            row0 = shard * fire.shape[0]
            return bridge.local_step(stamp, key, fire, states, params, policy_actions, shard, row0)

        rows, whole = P(axis), P()
        # the callback's outputs are per shard, which the varying-axes check cannot see
        self._mapped = jax.shard_map(
            local,
            mesh=mesh,
            in_specs=(whole, whole, rows, rows, rows, rows),
            out_specs=(rows, rows, rows),
            check_vma=False,
        )

    def init(self, batch: int, episode: Array | None = None) -> Array:
        return self.bridge.init(batch, episode)

    def step(self, carry, key, fire, states, params, policy_actions):
        actions, used, status = self._mapped(carry, key, fire, states, params, policy_actions)
        return carry, actions, used, status

    def finish(self, carry: Array) -> None:
        return self.bridge.finish(carry)

    def stats(self) -> dict[str, Any]:
        return self.bridge.stats()

    def reset_stats(self) -> None:
        self.bridge.reset_stats()

    def reset_memory(self) -> None:
        self.bridge.reset_memory()

    def close(self) -> None:
        self.bridge.close()


def make_mpc_bridge(env: NavEnv, cfg: MPCConfig | None = None) -> MPCBridge:
    """The MPC bridge of method §6 for an env (see `MPCBridge`)."""
    return MPCBridge(env, cfg or MPCConfig())
