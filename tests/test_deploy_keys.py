"""A key where the deploy API takes one (`infer_z`, `act`, `__call__`, `prior_z`,
`Adapter.init`) is a PRNG key or None: an int seed or another array is a TypeError naming `key`,
on the exported policy, the loaded one and the adapter alike, not JAX's "invalid PRNG key
data"."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

from mpcpearl_jax.deploy.adapter import Adapter, Scene
from mpcpearl_jax.deploy.exported import load_exported
from mpcpearl_jax.deploy.policy import load_policy
from mpcpearl_jax.envs import make_tasks

RUN = Path(__file__).resolve().parents[1] / "results/restaurant/mpc-pearl-eps0.2"
BAD = [3, 3.0, jnp.zeros(2), jnp.zeros(5, jnp.uint32)]
MATCH = r"^key: expected a PRNG key .* or None, got "


@pytest.fixture(scope="module")
def policies():
    return load_exported(RUN / "policy.export"), load_policy(RUN)


@pytest.mark.parametrize("key", BAD)
def test_a_key_that_is_not_one_is_named(policies, key):
    exported, loaded = policies
    obs = jnp.zeros(exported.obs_dim)
    ctx = jnp.zeros((4, exported.context_dim))
    mask = jnp.ones(4)
    with pytest.raises(TypeError, match=MATCH):
        exported.infer_z(ctx, mask, key)
    with pytest.raises(TypeError, match=MATCH):
        exported(obs, ctx, mask, key)
    with pytest.raises(TypeError, match=MATCH):
        loaded.infer_z(ctx, mask, key)
    with pytest.raises(TypeError, match=MATCH):
        loaded.act(obs, jnp.zeros(loaded.latent_dim), key)
    with pytest.raises(TypeError, match=MATCH):
        loaded(obs, ctx, key)
    with pytest.raises(TypeError, match=MATCH):
        loaded.prior_z(key)


def test_keys_of_both_kinds_and_none_are_taken(policies):
    exported, loaded = policies
    ctx = jnp.zeros((4, exported.context_dim))
    for key in (None, jax.random.PRNGKey(3), jax.random.key(3)):
        assert exported.infer_z(ctx, None, key).shape == (exported.latent_dim,)
        assert loaded.infer_z(ctx, None, key).shape == (loaded.latent_dim,)
        assert loaded.prior_z(key).shape == (loaded.latent_dim,)
    same = exported.infer_z(ctx, None, jax.random.PRNGKey(3))
    assert jnp.allclose(same, exported.infer_z(ctx, None, jax.random.PRNGKey(3)))


def test_adapter_init_names_a_bad_key(policies):
    exported, _ = policies
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test"))
    adapter = Adapter(exported)
    with pytest.raises(TypeError, match=MATCH):
        adapter.init(Scene.from_task(task), 3)
    adapter.init(Scene.from_task(task), jax.random.PRNGKey(0))
