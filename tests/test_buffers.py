"""The per-task ring buffers (pearl/buffers.py): inserts against a NumPy reference."""

import jax
import jax.numpy as jnp
import numpy as np

from mpcpearl_jax.pearl import Transitions, buffers

OBS, A = 5, 2


def _transitions(k, n, start=0.0):
    r = jnp.arange(k * n, dtype=jnp.float32).reshape(k, n) + start
    return Transitions(
        jnp.repeat(r[..., None], OBS, -1),
        jnp.repeat(r[..., None], A, -1),
        r,
        jnp.repeat(r[..., None], OBS, -1),
        jnp.zeros((k, n)),
    )


def _insert_ref(store, size, ptr, cap, task_ids, reward):
    """NumPy reference: append the rewards of each task to its ring buffer, in order."""
    store, size, ptr = store.copy(), size.copy(), ptr.copy()
    for i, t in enumerate(task_ids):
        for v in reward[i]:
            store[t, ptr[t]] = v
            ptr[t] = (ptr[t] + 1) % cap
            size[t] = min(size[t] + 1, cap)
    return store, size, ptr


def test_insert_matches_numpy_ring_buffer():
    rng = np.random.default_rng(0)
    cap, n_tasks, n = 7, 4, 5
    buf = buffers.init_buffer(n_tasks, cap, OBS, A)
    store = np.zeros((n_tasks, cap), np.float32)
    size = np.zeros(n_tasks, np.int64)
    ptr = np.zeros(n_tasks, np.int64)
    for step in range(6):  # wraps around several times
        ids = rng.choice(n_tasks, 2, replace=False)
        data = _transitions(2, n, start=100.0 * step)
        buf = jax.jit(buffers.insert)(buf, jnp.asarray(ids), data)
        store, size, ptr = _insert_ref(store, size, ptr, cap, ids, np.asarray(data.reward))
        np.testing.assert_array_equal(np.asarray(buf.size), size)
        np.testing.assert_array_equal(np.asarray(buf.ptr), ptr)
        for t in range(n_tasks):  # only the valid slots are defined
            np.testing.assert_array_equal(
                np.asarray(buf.data.reward)[t, : size[t]], store[t, : size[t]]
            )
            np.testing.assert_array_equal(
                np.asarray(buf.data.obs)[t, : size[t], 0], store[t, : size[t]]
            )
