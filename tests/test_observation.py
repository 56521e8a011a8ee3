"""The observation options (envs/observation.py) against NumPy references: velocities,
egocentric entries, sensing radius, people nearest first, the clock."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.errors import ConfigError


def test_velocity_observation_matches_numpy():
    from mpcpearl_jax.envs import make_env, make_tasks

    base = make_env("restaurant")
    env = make_env("restaurant", observe_velocity=True)
    tasks = make_tasks("restaurant", "test", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[5], tasks)
    h = np.asarray(task.human_pos)  # [T + 1, H, 2]
    nh = h.shape[1]
    assert env.obs_dim(tasks) == base.obs_dim(tasks) + 2 * nh
    obs, state = env.reset(jax.random.PRNGKey(0), task)
    obs0, _ = base.reset(jax.random.PRNGKey(0), task)
    np.testing.assert_array_equal(obs[3 + 2 * nh : 3 + 4 * nh], 0.0)  # no motion before t = 0
    np.testing.assert_allclose(obs[: 3 + 2 * nh], obs0[: 3 + 2 * nh])
    np.testing.assert_allclose(obs[3 + 4 * nh :], obs0[3 + 2 * nh :])  # tables unchanged
    for t in range(1, 12):
        state = state.replace(t=jnp.asarray(t, jnp.int32))
        got = np.asarray(env.observe(state, task))[3 + 2 * nh : 3 + 4 * nh]
        want = np.clip((h[t] - h[t - 1]) / (4.0 * 0.05), -1, 1).reshape(-1)
        np.testing.assert_allclose(got, want, atol=1e-5)
    assert np.abs(got).max() > 0.5  # people walk at ~3.2 m/s early on


def _ego_ref(pose, points, scale):
    d = np.asarray(points, np.float64) - pose[:2]
    c, s = np.cos(pose[2]), np.sin(pose[2])
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
    return np.clip(local / scale, -1, 1)


@pytest.mark.parametrize("env_name", ["restaurant", "sidewalk"])
def test_relative_observation_matches_numpy(env_name):
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.envs.types import EnvState

    base = make_env(env_name)
    env = make_env(env_name, observe_relative=True)
    tasks = make_tasks(env_name, "test", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[1], tasks)
    nh, ns = task.human_pos.shape[1], task.static_lo.shape[0]
    n0 = base.obs_dim(tasks)
    assert env.obs_dim(tasks) == n0 + 2 * (nh + ns + 1)
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(env.config.arena_lo), np.asarray(env.config.arena_hi)
    for t in (0, 7, 30):
        pose = np.array([*rng.uniform(lo + 0.5, hi - 0.5), rng.uniform(-np.pi, np.pi)])
        state = EnvState(pose=jnp.asarray(pose, jnp.float32), t=jnp.asarray(t, jnp.int32))
        got = np.asarray(env.observe(state, task))
        np.testing.assert_allclose(got[:n0], np.asarray(base.observe(state, task)), atol=1e-6)
        h, m = np.asarray(task.human_pos[t]), np.asarray(task.human_mask[t])
        want_h = np.where(m[:, None], _ego_ref(pose, h, 5.0), 1.0).reshape(-1)
        nearest = np.clip(pose[:2], np.asarray(task.static_lo), np.asarray(task.static_hi))
        want_s = _ego_ref(pose, nearest, 5.0).reshape(-1)
        want_g = _ego_ref(pose, np.asarray(task.goal)[None], 5.0).reshape(-1)
        np.testing.assert_allclose(got[n0:], np.concatenate([want_h, want_s, want_g]), atol=1e-5)
    # a point straight ahead of the robot is at (+d, 0) in its frame
    pose = np.array([0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(_ego_ref(pose, [[0.0, 2.0]], 5.0), [[0.4, 0.0]], atol=1e-12)


def test_sensing_radius_hides_far_people_everywhere_in_the_observation():
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.envs.types import EnvState

    full = make_env("restaurant", observe_velocity=True, observe_relative=True)
    env = make_env("restaurant", observe_velocity=True, observe_relative=True, sensing_radius=3.0)
    tasks = make_tasks("restaurant", "test", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[3], tasks)
    nh, ns = task.human_pos.shape[1], task.static_lo.shape[0]
    assert env.obs_dim(tasks) == full.obs_dim(tasks)
    rng = np.random.default_rng(1)
    hidden_seen = 0
    for t in (1, 10, 25, 60):
        pose = np.array([*rng.uniform(-4.0, 4.0, 2), rng.uniform(-np.pi, np.pi)])
        state = EnvState(pose=jnp.asarray(pose, jnp.float32), t=jnp.asarray(t, jnp.int32))
        got, ref = np.asarray(env.observe(state, task)), np.asarray(full.observe(state, task))
        h, m = np.asarray(task.human_pos[t]), np.asarray(task.human_mask[t])
        m_prev = np.asarray(task.human_mask[t - 1])
        seen = m & (np.linalg.norm(h - pose[:2], axis=-1) <= 3.0)
        hidden_seen += int((m & ~seen).sum())
        want_h = np.where(seen[:, None], np.clip(h / 5.0, -1, 1), -1.0).reshape(-1)
        np.testing.assert_allclose(got[3 : 3 + 2 * nh], want_h, atol=1e-5)
        vel = got[3 + 2 * nh : 3 + 4 * nh].reshape(nh, 2)
        np.testing.assert_array_equal(vel[~(seen & m_prev)], 0.0)
        np.testing.assert_allclose(
            vel[seen & m_prev],
            ref[3 + 2 * nh : 3 + 4 * nh].reshape(nh, 2)[seen & m_prev],
            atol=1e-6,
        )
        off = 3 + 4 * nh + 2 * ns  # egocentric people
        ego = got[off : off + 2 * nh].reshape(nh, 2)
        np.testing.assert_array_equal(ego[~seen], 1.0)
        np.testing.assert_allclose(
            ego[seen], ref[off : off + 2 * nh].reshape(nh, 2)[seen], atol=1e-6
        )
        np.testing.assert_allclose(got[off + 2 * nh :], ref[off + 2 * nh :], atol=1e-6)  # static
        np.testing.assert_allclose(got[:3], ref[:3], atol=1e-6)
    assert hidden_seen > 0  # the case under test occurred
    with pytest.raises(ConfigError, match="sensing_radius"):
        make_env("restaurant", sensing_radius=-1.0)


def test_sorted_observation_lists_people_nearest_first_in_every_part():
    """`observe_sorted` permutes the people of every part of the observation (positions,
    velocities, egocentric positions) by their distance to the robot, people out of sensing range
    last; a NumPy reference builds the same vector from the unsorted observation."""
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.envs.types import EnvState

    opts = dict(observe_velocity=True, observe_relative=True, sensing_radius=3.0, observe_time=True)
    plain, env = make_env("restaurant", **opts), make_env("restaurant", observe_sorted=True, **opts)
    tasks = make_tasks("restaurant", "val", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[5], tasks)
    nh, ns = task.human_pos.shape[1], task.static_lo.shape[0]
    assert env.obs_dim(tasks) == plain.obs_dim(tasks)
    rng = np.random.default_rng(3)
    permuted = 0
    for t in (0, 3, 12, 20, 33, 50, 79):
        pose = np.array([*rng.uniform(-3.0, 3.0, 2), rng.uniform(-np.pi, np.pi)])
        state = EnvState(pose=jnp.asarray(pose, jnp.float32), t=jnp.asarray(t, jnp.int32))
        got, ref = np.asarray(env.observe(state, task)), np.asarray(plain.observe(state, task))
        h, m = np.asarray(task.human_pos[t], np.float64), np.asarray(task.human_mask[t])
        d = np.linalg.norm(h - pose[:2], axis=-1)
        seen = m & (d <= 3.0)
        order = np.argsort(np.where(seen, d, np.inf), kind="stable")
        permuted += int(np.any(order != np.arange(nh)))
        off_v, off_e = 3 + 2 * nh, 3 + 4 * nh + 2 * ns
        want = ref.copy()
        for lo in (3, off_v, off_e):  # the three per-person blocks
            want[lo : lo + 2 * nh] = ref[lo : lo + 2 * nh].reshape(nh, 2)[order].reshape(-1)
        np.testing.assert_allclose(got, want, atol=1e-6)
        ds = np.where(seen, d, np.inf)[order]
        k = int(seen.sum())
        assert np.all(np.isfinite(ds[:k])) and np.all(np.diff(ds[:k]) >= 0)  # nearest first
        assert np.all(np.isinf(ds[k:]))  # the unseen last
    assert permuted >= 3  # the reordering under test occurred
    with pytest.raises(ConfigError, match="observe_sorted"):
        make_env("restaurant", observe_sorted=1)


def test_observe_time_appends_the_elapsed_fraction_and_changes_nothing_else():
    from mpcpearl_jax.envs import make_env, make_tasks

    plain = make_env("restaurant", observe_velocity=True)
    env = make_env("restaurant", observe_velocity=True, observe_time=True)
    tasks = make_tasks("restaurant", "val", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[2], tasks)
    assert env.obs_dim(tasks) == plain.obs_dim(tasks) + 1
    horizon = env.config.horizon
    actions = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (horizon, 2)), jnp.float32)
    key = jax.random.PRNGKey(0)
    (o, s), (p, q) = env.reset(key, task), plain.reset(key, task)
    for t in range(horizon):
        assert o.shape == (env.obs_dim(tasks),)
        np.testing.assert_allclose(o[-1], 2.0 * t / horizon - 1.0, atol=1e-6)
        np.testing.assert_array_equal(o[:-1], p)
        o, s, r, done, _ = env.step(key, s, actions[t], task)
        p, q, r_ref, _, _ = plain.step(key, q, actions[t], task)
        assert float(r) == float(r_ref)
    assert bool(done) and float(o[-1]) == 1.0


def _every_option():
    from mpcpearl_jax.envs.types import NavConfig

    return NavConfig(
        observe_velocity=True,
        observe_relative=True,
        observe_time=True,
        observe_forecast=2,
        forecast_stride=3,
        observe_presence=True,
    )


def test_the_layout_tiles_the_observation_and_each_option_adds_its_part_alone():
    """`PARTS` alone fixes the observation: the layout's parts tile it in order, and turning a
    part's option off removes that part's entries and leaves every other part's as they were."""
    import dataclasses

    from mpcpearl_jax.envs import make_env, make_tasks, observation

    full = _every_option()
    tasks = make_tasks("restaurant", "val", 0, config=full)
    task = jax.tree_util.tree_map(lambda x: x[2], tasks)
    h, s = task.human_pos.shape[-2], task.static_lo.shape[-2]

    def parts_of(config):
        env = make_env("restaurant", **{f: getattr(config, f) for f in observation.OPTIONS})
        obs, state = env.reset(jax.random.PRNGKey(0), task)
        obs, *_ = env.step(jax.random.PRNGKey(0), state, jnp.asarray([0.5, 0.1]), task)
        lay = observation.layout(env.config, h, s)
        assert [p["start"] for p in lay] == [
            sum(q["size"] for q in lay[:i]) for i in range(len(lay))
        ]
        assert sum(p["size"] for p in lay) == obs.shape[0] == observation.obs_dim(env.config, h, s)
        return {p["name"]: np.asarray(obs[p["start"] : p["start"] + p["size"]]) for p in lay}

    every = parts_of(full)
    assert list(every) == [p.name for p in observation.PARTS]
    for p in observation.PARTS:
        if p.option is None:
            continue
        off = {p.option: type(getattr(full, p.option))(0)}
        if p.option == "observe_relative":  # the forecast is egocentric
            off["observe_forecast"] = 0
        fewer = parts_of(dataclasses.replace(full, **off))
        assert p.name not in fewer
        for name, entries in fewer.items():
            np.testing.assert_array_equal(entries, every[name], err_msg=f"{p.option}: {name}")


def test_every_part_is_documented_and_grouped():
    """The observation's docstring names every part; every part belongs to one entity; the
    options an exported policy records include every part's option and scales."""
    from mpcpearl_jax.envs import observation

    doc = observation.observation.__doc__ or ""
    missing = [p.name for p in observation.PARTS if p.name not in doc]
    assert not missing, f"observation's docstring lacks {missing}"
    grouped = [n for e in observation.ENTITIES for n in observation.group(e)]
    assert sorted(grouped) == sorted(observation.PART)
    for p in observation.PARTS:
        assert {p.option, *p.scales} - {None} <= set(observation.OPTIONS)
        assert p.meaning(_every_option())


def test_missing_options_names_the_option_of_each_absent_part():
    from mpcpearl_jax.envs import observation

    assert observation.missing_options(["people_ego"], ["people_ego", "people_present"]) == [
        "observe_presence"
    ]
    assert observation.missing_options([], ["people_ego", "goal_ego"]) == ["observe_relative"]
    assert observation.missing_options([], ["robot_xy"]) == []


def test_config_validation_reads_the_layout_without_the_networks():
    """Checking a crowd encoder's inputs needs the observation's layout, not flax's networks."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from mpcpearl_jax.config import resolve\n"
        "from mpcpearl_jax.errors import ConfigError\n"
        "try:\n"
        "    resolve('default', overrides=['pearl.crowd_encoder=deepsets'])\n"
        "except ConfigError as e:\n"
        "    assert 'env.observe_presence=true' in str(e), e\n"
        "else:\n"
        "    raise SystemExit('no error')\n"
        "print(sorted(m for m in ('mpcpearl_jax.pearl.networks', 'distrax') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
