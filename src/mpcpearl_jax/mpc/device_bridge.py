"""The MPC of method §6 inside the jitted step: GP prediction and SQP on the device (`mpc.solver =
"device"`), no host callback.

The per-row warm-start memory of the host bridge is a JAX value (`DeviceMemory`) that the caller
carries through its `lax.scan` over time: a row whose t is its plan's t + 1 starts from the shifted
plan, otherwise cold. A scan starts from `init_memory`, so no plan outlives the batch of episodes
of one call (the host bridge's episode stamp). Fallbacks and status codes are the host bridge's:
a row whose solve is not safe (unsafe, QP failed, non-finite) applies its shifted previous plan if
it has one, else the policy's action. Counters (status, reasons, QPs) accumulate in the memory
and reach the host once per scan (`MPCBridge.record_counts`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.mpc import device_solver as ds
from mpcpearl_jax.mpc.solver import RowProblem

NOT_FIRED, SOLVED, FALLBACK_PLAN, FALLBACK_POLICY = range(4)  # as mpc.bridge
NO_PLAN = -10
# counters in DeviceMemory.counts: calls, rows, 4 status codes, the reasons, QP iterations, QPs
COUNT_NAMES = ("calls", "rows", *(f"status{i}" for i in range(4)), *ds.REASONS, "qp_iters", "n_qp")


class DeviceMemory(NamedTuple):
    """plans [B, K, 2] physical, plan_t [B] int32 (NO_PLAN: none), counts [len(COUNT_NAMES)]."""

    plans: Array
    plan_t: Array
    counts: Array


def init_memory(batch: int, horizon: int) -> DeviceMemory:
    """No plans, zero counters."""
    return DeviceMemory(
        jnp.zeros((batch, horizon, 2), jnp.float32),
        jnp.full((batch,), NO_PLAN, jnp.int32),
        jnp.zeros((len(COUNT_NAMES),), jnp.int32),
    )


def shifted(plans: Array) -> Array:
    """Each plan [.., K, 2] shifted by one step (its last input repeated)."""
    return jnp.concatenate([plans[..., 1:, :], plans[..., -1:, :]], axis=-2)


def merge(mem: DeviceMemory, fire: Array, t: Array, res: ds.DeviceResult):
    """New plans and the per-row status and physical input of a solved batch (res over all B
    rows; only fired rows change)."""
    warm = mem.plan_t == t - 1
    shift = shifted(mem.plans)
    status = jnp.where(res.ok, SOLVED, jnp.where(warm, FALLBACK_PLAN, FALLBACK_POLICY))
    status = jnp.where(fire, status, NOT_FIRED).astype(jnp.int32)
    ok = status == SOLVED
    back = status == FALLBACK_PLAN
    plans = jnp.where(ok[:, None, None], res.u, jnp.where(back[:, None, None], shift, mem.plans))
    plan_t = jnp.where(ok | back, t, jnp.where(status == FALLBACK_POLICY, NO_PLAN, mem.plan_t))
    u0 = jnp.where(ok[:, None], res.u[:, 0], jnp.where(back[:, None], shift[:, 0], 0.0))
    return plans, plan_t.astype(jnp.int32), status, u0


def count(fire: Array, status: Array, res: ds.DeviceResult) -> Array:
    """This step's counters (see COUNT_NAMES) over the fired rows."""
    f = fire.astype(jnp.int32)
    st = jnp.sum(f[:, None] * (status[:, None] == jnp.arange(4)), axis=0)
    rs = jnp.sum(f[:, None] * (res.reason[:, None] == jnp.arange(len(ds.REASONS))), axis=0)
    head = jnp.stack([jnp.any(fire).astype(jnp.int32), f.sum()])
    tail = jnp.stack([jnp.sum(f * res.qp_iters), jnp.sum(f * res.n_qp)])
    return jnp.concatenate([head, st, rs, tail]).astype(jnp.int32)


def solve_rows(solve, mem, idx, states, params, samples, valid) -> ds.DeviceResult:
    """The device SQP on rows idx [n] (indices past the batch are padding), from their shifted
    plans where made at t - 1, else cold."""
    take = lambda x: jnp.take(x, idx, axis=0, mode="clip")  # noqa: E731
    t = take(states.t)
    prob = RowProblem(
        take(states.pose).astype(jnp.float32),
        take(params.goal).astype(jnp.float32),
        take(samples).astype(jnp.float32),
        take(valid),
        take(params.static_lo).astype(jnp.float32),
        take(params.static_hi).astype(jnp.float32),
        take(params.static_radius).astype(jnp.float32),
    )
    warm = take(mem.plan_t) == t - 1
    return solve(prob, shifted(take(mem.plans)), warm)


def scatter(batch: int, idx: Array, part: ds.DeviceResult) -> ds.DeviceResult:
    """Rows idx of a batch of `batch` rows (the others: not ok, zeros)."""

    def put(x):
        full = jnp.zeros((batch, *x.shape[1:]), x.dtype)
        return full.at[idx].set(x, mode="drop")

    return jax.tree_util.tree_map(put, part)
