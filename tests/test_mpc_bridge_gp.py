"""The bridge predicts people only for fired rows, with the same samples as a full prediction."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax import make_env, make_tasks
from mpcpearl_jax.envs.types import EnvState
from mpcpearl_jax.mpc import MPCConfig, make_mpc_bridge


@pytest.mark.parametrize("fired", [[3, 50, 63], list(range(0, 64, 2))])  # few, and over the cap
def test_fired_row_prediction_equals_full_prediction(fired):
    env = make_env("restaurant")
    tasks = make_tasks("restaurant", "test")
    batch = 64
    params = jax.tree_util.tree_map(lambda x: x[jnp.arange(batch) % 24], tasks)
    states = EnvState(pose=params.start, t=jnp.arange(batch, dtype=jnp.int32) % 40)
    bridge = make_mpc_bridge(env, MPCConfig(gp_mode="fixed", num_samples=40))
    fire = jnp.zeros(batch, bool).at[jnp.array(fired)].set(True)
    key = jax.random.PRNGKey(7)
    full_s, full_v = jax.jit(bridge.predict)(key, states, params)
    part_s, part_v = jax.jit(bridge.predict_fired)(key, fire, states, params)
    idx = np.array(fired)
    np.testing.assert_allclose(part_s[idx], full_s[idx], rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(part_v[idx], full_v[idx])
