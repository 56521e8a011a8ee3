"""The brax `Env` adapter: the interface, brax's training wrappers and a tiny brax PPO run."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

# brax is an optional extra (`brax`; the `dev` extra includes it, so the suite tests the adapter)
brax_base = pytest.importorskip(
    "brax.envs.base", reason='brax not installed (an optional extra): pip install -e ".[brax]"'
)

from mpcpearl_jax.envs import make_env, make_tasks  # noqa: E402
from mpcpearl_jax.envs.brax_adapter import BraxNavEnv, wrap_for_training  # noqa: E402


@pytest.fixture(scope="module")
def tasks():
    return make_tasks("restaurant", "test", seed=0)


@pytest.fixture(scope="module")
def env(tasks):
    return BraxNavEnv(make_env("restaurant"), tasks)


def _take(params, i):
    return jax.tree_util.tree_map(lambda x: x[i], params)


def test_interface(env):
    assert isinstance(env, brax_base.Env)
    assert env.observation_size == 25 and env.action_size == 2 and env.backend == "jax"
    assert env.num_tasks == 24 and env.horizon == 80
    with pytest.raises(TypeError, match="NavEnv"):
        BraxNavEnv("restaurant", make_tasks("restaurant", "test"))  # type: ignore[arg-type]


def test_steps_match_the_nav_env(env, tasks):
    nav = make_env("restaurant")
    state = jax.jit(env.reset)(jax.random.PRNGKey(3))
    task = int(state.info["task"])
    params = _take(tasks, task)
    obs, nav_state = nav.reset(jax.random.PRNGKey(0), params)
    np.testing.assert_allclose(state.obs, obs, atol=1e-6)
    step = jax.jit(env.step)
    rng = np.random.default_rng(0)
    for t in range(12):
        a = jnp.asarray(rng.uniform(-1, 1, 2), jnp.float32)
        state = step(state, a)
        obs, nav_state, r, _, info = nav.step(jax.random.PRNGKey(t), nav_state, a, params)
        np.testing.assert_allclose(state.obs, obs, atol=1e-6)
        np.testing.assert_allclose(state.reward, r, atol=1e-5)
        assert float(state.metrics["collision"]) == float(info.collision)
        assert float(state.done) == 0.0 and int(state.info["task"]) == task
    assert int(state.pipeline_state.t) == 12


def test_reset_samples_tasks_and_single_task_works(env, tasks):
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    drawn = np.asarray(jax.jit(jax.vmap(env.reset))(keys).info["task"])
    assert drawn.min() >= 0 and drawn.max() < 24 and len(np.unique(drawn)) > 12
    one = BraxNavEnv(make_env("restaurant"), _take(tasks, 5))
    assert one.num_tasks == 1
    state = one.reset(jax.random.PRNGKey(1))
    assert int(state.info["task"]) == 0
    np.testing.assert_allclose(one.task_params(0).human_pos, tasks.human_pos[5])


def test_brax_training_wrappers_and_jitted_rollout(env):
    wrapped = wrap_for_training(env)  # VmapWrapper, EpisodeWrapper(80), AutoResetWrapper
    batch, steps = 6, 2 * env.horizon + 5
    state0 = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
    assert state0.obs.shape == (batch, 25)

    @jax.jit
    def rollout(state, key):
        def body(s, k):
            a = jax.random.uniform(k, (batch, 2), minval=-1.0, maxval=1.0)
            s = wrapped.step(s, a)
            out = (s.done, s.reward, s.pipeline_state.t, s.info["task"], s.obs)
            return s, out

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    final, (done, reward, t, task, obs) = rollout(state0, jax.random.PRNGKey(1))
    done = np.asarray(done)
    # the episode ends exactly every `horizon` steps (no early termination), for every slot
    ends = np.where(done[:, 0])[0] + 1
    np.testing.assert_array_equal(ends, [env.horizon, 2 * env.horizon])
    assert np.all(done == done[:, :1])
    # auto-reset restores the first state: t back to 0, first observation, same task per slot
    after = env.horizon - 1
    np.testing.assert_array_equal(np.asarray(t)[after], 0)
    np.testing.assert_allclose(obs[after], state0.obs)
    np.testing.assert_array_equal(
        np.asarray(task), np.broadcast_to(state0.info["task"], task.shape)
    )
    assert np.all(np.asarray(t)[: env.horizon - 1] == np.arange(1, env.horizon)[:, None])
    assert np.isfinite(np.asarray(reward)).all()


def _allow_brax_pmap_helpers(monkeypatch):
    """brax 0.14 trainers call jax.device_put_replicated/_sharded, removed from JAX 0.10's API."""
    import jax._src.api as jax_api

    for name in ("device_put_replicated", "device_put_sharded"):
        try:
            getattr(jax, name)
        except AttributeError:
            monkeypatch.setattr(jax, name, getattr(jax_api, name), raising=False)


@pytest.mark.slow  # Brax's PPO end to end (~25 s); the adapter's env is tested fast
def test_brax_ppo_runs_on_the_task_distribution(env, monkeypatch):
    _allow_brax_pmap_helpers(monkeypatch)
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo

    factory = functools.partial(
        ppo_networks.make_ppo_networks,
        policy_hidden_layer_sizes=(16,),
        value_hidden_layer_sizes=(16,),
    )
    make_policy, params, metrics = ppo.train(
        env,
        num_timesteps=1600,
        episode_length=env.horizon,
        num_envs=8,
        batch_size=8,
        num_minibatches=2,
        unroll_length=10,
        num_updates_per_batch=1,
        num_evals=1,
        num_eval_envs=4,
        network_factory=factory,
        seed=0,
    )
    assert np.isfinite(metrics["eval/episode_reward"])
    for name in ("collision", "in_goal", "n_dynamic", "n_static"):
        assert f"eval/episode_{name}" in metrics
    policy = make_policy(params, deterministic=True)
    state = env.reset(jax.random.PRNGKey(0))
    action, _ = policy(state.obs, jax.random.PRNGKey(1))
    assert action.shape == (2,) and np.all(np.abs(np.asarray(action)) <= 1.0)
