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
    num_tasks: int,
    capacity: int,
    obs_dim: int,
    action_dim: int,
    lead: tuple[int, ...] = (),
    expert: bool = False,
) -> TaskBuffer:
    """Empty buffers [*lead, N, cap, ...]; every leaf is its own device array (no aliasing).
    `expert`: the buffers also keep each transition's `expert` mark (`pearl.imitation`)."""
    z = lambda *s: jnp.zeros((*lead, num_tasks, capacity, *s), jnp.float32)  # noqa: E731
    data = Transitions(z(obs_dim), z(action_dim), z(), z(obs_dim), z(), z() if expert else None)
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


def sample(buf: TaskBuffer, key: Array, task_ids: Array, n: int) -> Transitions:
    """Uniform sample with replacement of `n` transitions for each of `task_ids` [k] -> [k, n].

    Tasks with an empty buffer return row 0 (callers only sample filled tasks).
    """
    hi = jnp.maximum(buf.size[task_ids], 1)[:, None]
    idx = jax.random.randint(key, (task_ids.shape[0], n), 0, hi)
    rows = task_ids[:, None]
    return jax.tree_util.tree_map(lambda b: b[rows, idx], buf.data)
