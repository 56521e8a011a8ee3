"""The per-task ring buffers (pearl/buffers.py): masked inserts against a NumPy reference."""

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


def _insert_masked_ref(store, size, ptr, cap, task_ids, reward, mask):
    """NumPy reference: append the kept rewards of each task to its ring buffer, in order."""
    store, size, ptr = store.copy(), size.copy(), ptr.copy()
    for i, t in enumerate(task_ids):
        for v in reward[i][mask[i]]:
            store[t, ptr[t]] = v
            ptr[t] = (ptr[t] + 1) % cap
            size[t] = min(size[t] + 1, cap)
    return store, size, ptr


def test_insert_masked_matches_numpy_ring_buffer():
    rng = np.random.default_rng(0)
    cap, n_tasks, n = 7, 4, 5
    buf = buffers.init_buffer(n_tasks, cap, OBS, A)
    store = np.zeros((n_tasks, cap), np.float32)
    size = np.zeros(n_tasks, np.int64)
    ptr = np.zeros(n_tasks, np.int64)
    for step in range(6):  # wraps around several times
        ids = rng.choice(n_tasks, 2, replace=False)
        data = _transitions(2, n, start=100.0 * step)
        mask = rng.uniform(size=(2, n)) < 0.6
        buf = jax.jit(buffers.insert_masked)(buf, jnp.asarray(ids), data, jnp.asarray(mask))
        store, size, ptr = _insert_masked_ref(
            store, size, ptr, cap, ids, np.asarray(data.reward), mask
        )
        np.testing.assert_array_equal(np.asarray(buf.size), size)
        np.testing.assert_array_equal(np.asarray(buf.ptr), ptr)
        for t in range(n_tasks):  # only the valid slots are defined
            np.testing.assert_array_equal(
                np.asarray(buf.data.reward)[t, : size[t]], store[t, : size[t]]
            )
            np.testing.assert_array_equal(
                np.asarray(buf.data.obs)[t, : size[t], 0], store[t, : size[t]]
            )


def test_insert_masked_all_true_equals_insert():
    buf = buffers.init_buffer(3, 6, OBS, A)
    data = _transitions(2, 4)
    ids = jnp.array([2, 0])
    a = buffers.insert(buffers.insert(buf, ids, data), ids, data)
    m = jnp.ones((2, 4), bool)
    b = buffers.insert_masked(buffers.insert_masked(buf, ids, data, m), ids, data, m)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
