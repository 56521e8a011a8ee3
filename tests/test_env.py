"""The JAX navigation env: no retracing, vmap over tasks and keys, clear errors, invariants."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from mpcpearl_jax.envs import ConfigError, EnvState, NavConfig, make_env, make_tasks


@pytest.fixture(scope="module")
def env():
    return make_env("restaurant")


@pytest.fixture(scope="module")
def tasks():
    return make_tasks("restaurant", "test", seed=0)


def _take(params, i):
    return jax.tree_util.tree_map(lambda x: x[i], params)


def _random_state(rng, cfg):
    lo = np.asarray(cfg.arena_lo) + cfg.robot_radius
    hi = np.asarray(cfg.arena_hi) - cfg.robot_radius
    pose = np.array([*rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi)], np.float32)
    return EnvState(pose=jnp.asarray(pose), t=jnp.int32(rng.integers(cfg.horizon)))


def test_jitted_step_traces_once(env, tasks):
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(key, state, action, params):
        return env.step(key, state, action, params)

    rng = np.random.default_rng(0)
    for i in range(6):
        state = _random_state(rng, env.config)
        action = jnp.asarray(rng.uniform(-2, 2, 2), jnp.float32)
        step(jax.random.PRNGKey(i), state, action, _take(tasks, i))
    # a whole episode through the same compiled step
    obs, state = env.reset(jax.random.PRNGKey(0), _take(tasks, 3))
    for t in range(5):
        obs, state, *_ = step(jax.random.PRNGKey(t), state, jnp.zeros(2), _take(tasks, 3))
    assert int(state.t) == 5


def test_vmap_over_two_task_axes_equals_loop(env, tasks):
    grid = jax.tree_util.tree_map(lambda x: x[:6].reshape((2, 3) + x.shape[1:]), tasks)
    rng = np.random.default_rng(1)
    poses = rng.uniform(-4, 4, (2, 3, 3)).astype(np.float32)
    state = EnvState(pose=jnp.asarray(poses), t=jnp.asarray(rng.integers(0, 79, (2, 3)), jnp.int32))
    actions = jnp.asarray(rng.uniform(-1.2, 1.2, (2, 3, 2)), jnp.float32)
    key = jax.random.PRNGKey(0)
    step = jax.vmap(jax.vmap(env.step, in_axes=(None, 0, 0, 0)), in_axes=(None, 0, 0, 0))
    batched = jax.jit(step)(key, state, actions, grid)
    assert batched[0].shape == (2, 3, 25) and batched[2].shape == (2, 3)
    for i in range(2):
        for j in range(3):
            s = jax.tree_util.tree_map(lambda x, i=i, j=j: x[i, j], state)
            one = env.step(key, s, actions[i, j], _take(tasks, 3 * i + j))
            got = jax.tree_util.tree_map(lambda x, i=i, j=j: x[i, j], batched)
            chex.assert_trees_all_close(got, one, atol=1e-6)


def test_vmap_over_keys_equals_loop(env, tasks):
    params = _take(tasks, 0)

    def policy(key, obs):
        del obs
        return jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0)

    keys = jax.random.split(jax.random.PRNGKey(7), 4)
    rollout = jax.jit(lambda k: env.rollout(k, params, policy))
    batched = jax.jit(jax.vmap(lambda k: env.rollout(k, params, policy)))(keys)
    assert batched["position"].shape == (4, env.config.horizon + 1, 2)
    for i in range(4):
        one = rollout(keys[i])
        chex.assert_trees_all_close(jax.tree_util.tree_map(lambda x, i=i: x[i], batched), one)
    # different keys give different episodes
    assert not np.allclose(batched["position"][0], batched["position"][1])


def test_obs_shape_and_range(env, tasks):
    obs, state = env.reset(jax.random.PRNGKey(0), _take(tasks, 0))
    assert obs.shape == (env.obs_dim(tasks),) == (25,)
    assert obs.dtype == jnp.float32
    assert np.all(np.abs(obs) <= 1.0)
    np.testing.assert_allclose(obs[:3], [-0.9, 0.9, -1 / 8], atol=1e-6)


# ------------------------------------------------------------------ errors
def test_unknown_env_name():
    with pytest.raises(ValueError, match="unknown env name 'kitchen'.*restaurant"):
        make_env("kitchen")
    with pytest.raises(ValueError, match="unknown env name"):
        make_tasks("kitchen", "train")


def test_unknown_split():
    with pytest.raises(ValueError, match="unknown split 'validation'.*train"):
        make_tasks("restaurant", "validation")


def test_unknown_config_override():
    with pytest.raises(ConfigError, match="no field.*'speed'"):
        make_env("restaurant", speed=3.0)


@pytest.mark.parametrize("shape", [(3,), (1, 2), (), (4, 2)])
def test_wrong_action_shape(env, tasks, shape):
    _, state = env.reset(jax.random.PRNGKey(0), _take(tasks, 0))
    msg = r"action must have shape \(2,\).*got"
    with pytest.raises(ValueError, match=msg):
        env.step(jax.random.PRNGKey(0), state, jnp.zeros(shape), _take(tasks, 0))
    with pytest.raises(ValueError, match=msg):  # the same message under jit
        jax.jit(env.step)(jax.random.PRNGKey(0), state, jnp.zeros(shape), _take(tasks, 0))


@pytest.mark.parametrize(
    "field, value",
    [
        ("dt", -0.05),
        ("dt", float("nan")),
        ("v_max", 0.0),
        ("horizon", 0),
        ("horizon", 80.5),
        ("r_safe", -0.1),
        ("w_goal", float("inf")),
        ("arena_lo", (0.0,)),
        ("arena_hi", (-4.9, -4.9)),
    ],
)
def test_config_validation_names_the_field(field, value):
    with pytest.raises(ConfigError, match=rf"NavConfig\.{field}"):
        NavConfig(**{field: value})


def test_config_is_frozen_and_replace_validates():
    cfg = NavConfig()
    with pytest.raises(AttributeError):
        cfg.dt = 0.1  # type: ignore[misc]
    assert cfg.replace(r_safe=0.125).r_safe == 0.125
    with pytest.raises(ConfigError, match="NavConfig.robot_radius"):
        cfg.replace(robot_radius=-1.0)


def test_navenv_rejects_non_config():
    from mpcpearl_jax.envs import NavEnv

    with pytest.raises(TypeError, match="NavConfig"):
        NavEnv({"dt": 0.05})  # type: ignore[arg-type]


# ---------------------------------------------------------- property tests
_ENV = make_env("restaurant")
_TASKS = make_tasks("restaurant", "test", seed=0)
_STEP = jax.jit(_ENV.step)
_CFG = _ENV.config
_coord = st.floats(-4.75, 4.75, width=32)
_PI32 = float(np.float32(np.pi))
_angle = st.floats(-_PI32, _PI32, width=32, exclude_max=True)
_act = st.floats(-5.0, 5.0, width=32)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    x=_coord,
    y=_coord,
    theta=_angle,
    t=st.integers(0, _CFG.horizon - 1),
    a0=_act,
    a1=_act,
    task=st.integers(0, 23),
)
@example(x=0.0, y=-4.0, theta=-_PI32, t=0, a0=-1.0, a1=0.0, task=0)  # at rest on -pi
@example(x=4.75, y=-4.75, theta=0.0, t=10, a0=5.0, a1=0.0, task=1)  # driving into the wall
def test_step_invariants(x, y, theta, t, a0, a1, task):
    params = _take(_TASKS, task)
    state = EnvState(pose=jnp.array([x, y, theta], jnp.float32), t=jnp.int32(t))
    obs, nstate, r, done, info = _STEP(
        jax.random.PRNGKey(0), state, jnp.array([a0, a1], jnp.float32), params
    )
    pose = np.asarray(nstate.pose)
    # heading wrapped to [-pi, pi) (pi as a float32)
    assert -_PI32 <= pose[2] < _PI32
    # position inside the arena shrunk by the robot radius
    lo = np.asarray(_CFG.arena_lo) + _CFG.robot_radius
    hi = np.asarray(_CFG.arena_hi) - _CFG.robot_radius
    assert np.all(pose[:2] >= lo - 1e-6) and np.all(pose[:2] <= hi + 1e-6)
    # no movement at all on a real collision
    if bool(info.collision):
        np.testing.assert_array_equal(pose, np.asarray(state.pose))
        assert float(r) <= -_CFG.w_dynamic + _CFG.w_goal  # a collision violates a threshold
    # reward never exceeds the goal bonus minus the (non-negative) position cost
    dist2 = float(np.sum((np.array([x, y]) - np.asarray(params.goal)) ** 2))
    assert float(r) <= _CFG.w_goal - _CFG.q_weight * dist2 / _CFG.cost_scale + 1e-5
    # observation in [-1, 1], time advances, no early termination
    assert np.all(np.abs(np.asarray(obs)) <= 1.0)
    assert int(nstate.t) == t + 1 and bool(done) == (t + 1 >= _CFG.horizon)
    np.testing.assert_allclose(info.position, pose[:2])


def _restaurant_task():
    from mpcpearl_jax.envs import make_env, make_tasks

    env = make_env("restaurant")
    tasks = make_tasks("restaurant", "train", 0, config=env.config)
    return env, jax.tree_util.tree_map(lambda x: x[0], tasks)


def test_random_start_is_free_in_the_arena_and_outside_the_goal():
    env, task = _restaurant_task()
    cfg = env.config
    poses = np.asarray(
        jax.vmap(lambda k: env.random_start(k, task))(jax.random.split(jax.random.PRNGKey(0), 400))
    )
    assert poses.shape == (400, 3) and np.all(np.isfinite(poses))
    assert np.all(np.abs(poses[:, 2]) <= np.pi)
    lo = np.asarray(cfg.arena_lo) + cfg.robot_radius
    hi = np.asarray(cfg.arena_hi) - cfg.robot_radius
    assert np.all(poses[:, :2] >= lo) and np.all(poses[:, :2] <= hi)
    # NumPy reference of the two exclusions: no table or person present at t = 0 within reach,
    # not inside the goal region
    hp, hm = np.asarray(task.human_pos[0]), np.asarray(task.human_mask[0])
    slo, shi = np.asarray(task.static_lo), np.asarray(task.static_hi)
    srad = np.asarray(task.static_radius)
    for p in poses[:, :2]:
        d_s = np.linalg.norm(np.maximum(np.maximum(slo - p, p - shi), 0.0), axis=-1) - srad
        assert np.all(d_s >= cfg.robot_radius)
        d_h = np.linalg.norm(hp - p, axis=-1)[hm]
        assert np.all(d_h >= cfg.robot_radius + cfg.human_radius)
        assert np.linalg.norm(p - np.asarray(task.goal)) > cfg.goal_radius
    # spread over the arena, not a handful of spots
    assert np.std(poses[:, 0]) > 2.0 and np.std(poses[:, 1]) > 2.0
    assert len(np.unique(np.round(poses[:, :2], 3), axis=0)) == 400


def test_random_start_falls_back_to_the_task_start_when_nothing_is_free():
    env, task = _restaurant_task()
    blocked = task.replace(  # one box over the whole arena: no candidate is free
        static_lo=task.static_lo.at[0].set(jnp.array([-5.0, -5.0])),
        static_hi=task.static_hi.at[0].set(jnp.array([5.0, 5.0])),
    )
    pose = env.random_start(jax.random.PRNGKey(3), blocked)
    np.testing.assert_array_equal(np.asarray(pose), np.asarray(task.start, np.float32))
