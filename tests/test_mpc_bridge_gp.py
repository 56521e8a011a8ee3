"""The bridge predicts people only for fired rows, with the same samples as a full prediction, and
hands the host only those rows while they fit the cap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax import make_env, make_tasks
from mpcpearl_jax.envs.types import EnvState
from mpcpearl_jax.mpc import HostSolver, MPCBridge, MPCConfig, SolveResult
from mpcpearl_jax.mpc.bridge import fired_cap


class SeenHost(HostSolver):
    """Records what each host call receives; every fired row 'solves' to standing still."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.calls = []

    def __call__(self, batch, idx, fired, pose, t, goal, lo, hi, rad, samples, valid, *rest):
        self.calls.append(
            (np.asarray(idx), np.asarray(fired), np.asarray(samples), np.asarray(valid))
        )
        return super().__call__(
            batch, idx, fired, pose, t, goal, lo, hi, rad, samples, valid, *rest
        )

    def solve_rows(self, probs, inits, num_static):
        k = self.cfg.horizon
        return [
            SolveResult(np.zeros((k, 2)), np.zeros((k + 1, 3)), True, "solved", 1, 1, 0.0, 0.0)
            for _ in probs
        ]


@pytest.mark.parametrize("fired", [[3, 50, 63], list(range(0, 64, 2))])  # few, and over the cap
def test_fired_row_prediction_equals_full_prediction(fired):
    env = make_env("restaurant")
    tasks = make_tasks("restaurant", "test")
    batch = 64
    params = jax.tree_util.tree_map(lambda x: x[jnp.arange(batch) % 24], tasks)
    states = EnvState(pose=params.start, t=jnp.arange(batch, dtype=jnp.int32) % 40)
    cfg = MPCConfig(gp_mode="fixed", num_samples=40)
    host = SeenHost(env.config, cfg)
    bridge = MPCBridge(env, cfg, host=host)
    fire = jnp.zeros(batch, bool).at[jnp.array(fired)].set(True)
    key = jax.random.PRNGKey(7)
    full_s, full_v = jax.jit(bridge.predict)(key, states, params)
    policy = jnp.zeros((batch, 2))
    _, _, used, status = jax.jit(bridge.step)(bridge.init(batch), key, fire, states, params, policy)
    np.testing.assert_array_equal(np.asarray(used), np.asarray(fire))
    [(idx, on, samples, valid)] = host.calls  # one call, with the cap's rows or the whole batch
    cap = fired_cap(batch)
    assert idx.shape == ((cap,) if len(fired) <= cap else (batch,)) and cap < batch
    np.testing.assert_array_equal(idx[on], fired)
    assert on.sum() == len(fired)
    np.testing.assert_allclose(samples[on], full_s[np.array(fired)], rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(valid[on], full_v[np.array(fired)])
