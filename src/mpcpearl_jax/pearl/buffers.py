"""Per-task replay buffers on device: fixed-size arrays with a task axis, jittable insert/sample.

Each task owns a ring buffer of `capacity` transitions. The RL buffer keeps everything; the
encoder buffer is reset on every visit of a task so that it holds only the most recent prior-z
collection (method §7; the sampler S_c of the paper).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct
from jax import Array

from mpcpearl_jax.pearl.types import Transitions


class TaskBuffer(struct.PyTreeNode):
    """Arrays: data fields [N, cap, ...]; size, ptr [N] int32."""

    data: Transitions
    size: Array
    ptr: Array

    @property
    def capacity(self) -> int:
        return int(self.data.reward.shape[-1])


def init_buffer(
    num_tasks: int, capacity: int, obs_dim: int, action_dim: int, lead: tuple[int, ...] = ()
) -> TaskBuffer:
    """Empty buffers [*lead, N, cap, ...]; every leaf is its own device array (no aliasing)."""
    z = lambda *s: jnp.zeros((*lead, num_tasks, capacity, *s), jnp.float32)  # noqa: E731
    data = Transitions(z(obs_dim), z(action_dim), z(), z(obs_dim), z())
    count = lambda: jnp.zeros((*lead, num_tasks), jnp.int32)  # noqa: E731
    return TaskBuffer(data, count(), count())


def clear(buf: TaskBuffer, task_ids: Array) -> TaskBuffer:
    """Empty the buffers of `task_ids` [k] (data is left in place and overwritten later)."""
    return buf.replace(size=buf.size.at[task_ids].set(0), ptr=buf.ptr.at[task_ids].set(0))


def insert(buf: TaskBuffer, task_ids: Array, data: Transitions) -> TaskBuffer:
    """Append `data` [k, n, ...] to the ring buffers of distinct `task_ids` [k]."""
    cap = buf.capacity
    n = data.reward.shape[1]
    idx = (buf.ptr[task_ids][:, None] + jnp.arange(n)[None, :]) % cap  # [k, n]
    rows = task_ids[:, None]
    new = jax.tree_util.tree_map(lambda b, d: b.at[rows, idx].set(d), buf.data, data)
    return TaskBuffer(
        new,
        buf.size.at[task_ids].set(jnp.minimum(buf.size[task_ids] + n, cap)),
        buf.ptr.at[task_ids].set((buf.ptr[task_ids] + n) % cap),
    )


def insert_masked(buf: TaskBuffer, task_ids: Array, data: Transitions, mask: Array) -> TaskBuffer:
    """Append only the rows of `data` [k, n, ...] where `mask` [k, n] is true, in order.

    The kept rows of each task are moved to the front (stable) and written at the ring pointer;
    the others are dropped (scatter with mode="drop"), so a full buffer loses only as many old
    transitions as new ones arrive.
    """
    cap = buf.capacity
    n = data.reward.shape[1]
    order = jnp.argsort(~mask, axis=1, stable=True)  # kept rows first
    count = jnp.sum(mask, axis=1).astype(jnp.int32)  # [k]
    j = jnp.arange(n)[None, :]
    idx = (buf.ptr[task_ids][:, None] + j) % cap
    idx = jnp.where(j < jnp.minimum(count, cap)[:, None], idx, cap)  # cap = out of range: dropped
    rows = task_ids[:, None]
    gather = lambda d: jnp.take_along_axis(  # noqa: E731
        d, order.reshape(order.shape + (1,) * (d.ndim - 2)), axis=1
    )
    new = jax.tree_util.tree_map(
        lambda b, d: b.at[rows, idx].set(gather(d), mode="drop"), buf.data, data
    )
    return TaskBuffer(
        new,
        buf.size.at[task_ids].set(jnp.minimum(buf.size[task_ids] + count, cap)),
        buf.ptr.at[task_ids].set((buf.ptr[task_ids] + count) % cap),
    )


def sample(buf: TaskBuffer, key: Array, task_ids: Array, n: int) -> Transitions:
    """Uniform sample with replacement of `n` transitions for each of `task_ids` [k] -> [k, n].

    Tasks with an empty buffer return row 0 (callers only sample filled tasks).
    """
    hi = jnp.maximum(buf.size[task_ids], 1)[:, None]
    idx = jax.random.randint(key, (task_ids.shape[0], n), 0, hi)
    rows = task_ids[:, None]
    return jax.tree_util.tree_map(lambda b: b[rows, idx], buf.data)


def sample_n_step(
    buf: TaskBuffer,
    key: Array,
    task_ids: Array,
    n: int,
    steps: int,
    gamma: float,
    horizon: int,
) -> Transitions:
    """Uniform sample of `n` n-step transitions per task of `task_ids` [k] -> [k, n]: from a
    row t, m = min(steps, horizon - t mod horizon) steps of its episode: reward
    sum_{j<m} gamma^j r_{t+j}, next_obs the observation after them, discount gamma^m
    (extension `PearlConfig.n_step`; no off-policy correction, as in Rainbow and RLPD's n-step).

    Needs every episode stored whole, in order, at an index that is a multiple of `horizon`:
    true of the replay buffer when its capacity is a multiple of the horizon (every insert is
    whole episodes). The start rows are drawn exactly as `sample` draws them (same key)."""
    cap = buf.capacity
    hi = jnp.maximum(buf.size[task_ids], 1)[:, None]
    idx = jax.random.randint(key, (task_ids.shape[0], n), 0, hi)  # as `sample`
    rows = task_ids[:, None]
    m = jnp.minimum(steps, horizon - idx % horizon)  # [k, n] steps left in the episode
    j = jnp.arange(steps)
    later = (idx[..., None] + j) % cap  # [k, n, steps]
    rewards = buf.data.reward[rows[..., None], later]
    weight = jnp.where(j < m[..., None], gamma ** j.astype(jnp.float32), 0.0)
    last = (idx + m - 1) % cap
    first = jax.tree_util.tree_map(lambda b: b[rows, idx], buf.data)
    return first._replace(
        reward=jnp.sum(weight * rewards, axis=-1),
        next_obs=buf.data.next_obs[rows, last],
        discount=gamma ** m.astype(jnp.float32),
    )
