"""The crowd encoder (`pearl.crowd_encoder` "attention") and the observation entries it reads
(`env.observe_forecast`, `env.observe_presence`): the forecast against a NumPy reference,
invariance to the order of the people, absent people masked out (not read), no NaN in an empty
crowd, the network spec round trip, one-line errors, and a tiny training whose policy
`load_policy` and the exported policy reproduce."""

from __future__ import annotations

import dataclasses
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.config import preset
from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.envs.observation import layout, obs_dim
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.pearl.config import PearlConfig
from mpcpearl_jax.pearl.networks import Networks

EGO = dict(observe_relative=True, observe_sorted=True, observe_velocity=True, observe_time=True)


def _env(**kw):
    return make_env("restaurant", **{**EGO, "sensing_radius": 3.0, **kw})


def _task(env, i=0):
    tasks = make_tasks("restaurant", "train", 0, config=env.config)
    return tasks, jax.tree_util.tree_map(lambda a: a[i], tasks)


def _state_at(env, task, t):
    from mpcpearl_jax.envs.types import EnvState

    return EnvState(pose=task.start.astype(jnp.float32), t=jnp.asarray(t, jnp.int32))


def test_forecast_and_presence_match_a_numpy_reference():
    env = _env(observe_forecast=3, forecast_stride=4, observe_presence=True, observe_sorted=False)
    tasks, task = _task(env)
    parts = {p["name"]: p for p in env.obs_layout(tasks)}
    assert sum(p["size"] for p in parts.values()) == env.obs_dim(tasks)
    cfg = env.config
    for t in (0, 1, 17, 40):
        obs = np.asarray(env.observe(_state_at(env, task, t), task))
        pose = np.asarray(task.start, np.float64)
        humans, mask = (np.asarray(a) for a in env.humans_at(task, jnp.asarray(t)))
        prev, prev_mask = (np.asarray(a) for a in env.humans_at(task, jnp.asarray(max(t - 1, 0))))
        mask = mask & (np.linalg.norm(humans - pose[:2], axis=-1) <= cfg.sensing_radius)
        want_f, want_p = [], []
        c, s = math.cos(pose[2]), math.sin(pose[2])
        for h in range(humans.shape[0]):
            want_p.append(1.0 if mask[h] else -1.0)
            v = humans[h] - prev[h] if (mask[h] and prev_mask[h]) else np.zeros(2)
            for k in (4, 8, 12):
                q = humans[h] + k * v - pose[:2]
                local = np.array([c * q[0] + s * q[1], -s * q[0] + c * q[1]]) / 5.0
                want_f.extend(np.clip(local, -1, 1) if mask[h] else (1.0, 1.0))
        f, p = parts["people_forecast"], parts["people_present"]
        np.testing.assert_allclose(obs[f["start"] : f["start"] + f["size"]], want_f, atol=1e-5)
        np.testing.assert_array_equal(obs[p["start"] : p["start"] + p["size"]], want_p)
    # with the new parts removed, the observation of the same options without them
    plain = _env(observe_sorted=False)
    drop = np.r_[f["start"] : f["start"] + f["size"], p["start"] : p["start"] + p["size"]]
    np.testing.assert_array_equal(
        np.delete(np.asarray(env.observe(_state_at(env, task, 17), task)), drop),
        np.asarray(plain.observe(_state_at(plain, task, 17), task)),
    )
    assert obs_dim(plain.config, 6, 5) + 6 * 3 * 2 + 6 == obs_dim(env.config, 6, 5)
    assert [q["name"] for q in layout(env.config, 6, 5)][-3:] == [
        "people_forecast",
        "people_present",
        "time",
    ]


def test_forecast_needs_the_egocentric_entries():
    with pytest.raises(ConfigError, match="observe_forecast"):
        make_env("restaurant", observe_forecast=2)
    with pytest.raises(ConfigError, match="forecast_stride"):
        make_env("restaurant", observe_relative=True, observe_forecast=2, forecast_stride=0)


def _nets(**kw):
    env = _env(observe_presence=True, **kw)
    tasks, task = _task(env)
    cfg = PearlConfig(hidden=(32, 32), crowd_encoder="attention", crowd_dim=16, crowd_heads=2)
    nets = Networks(cfg, env.obs_dim(tasks), 2, env.obs_layout(tasks))
    return env, tasks, nets, nets.init(jax.random.PRNGKey(0))


def _people_blocks(nets):
    """[(start, per-person size)] of the people's parts of the observation."""
    h = nets.crowd.num_people
    return [(s, k // h) for n, s, k in nets.crowd.layout if n.startswith("people_")]


def _permute(obs, nets, order):
    out = np.array(obs)
    for start, per in _people_blocks(nets):
        h = nets.crowd.num_people
        block = obs[..., start : start + h * per].reshape(*obs.shape[:-1], h, per)
        out[..., start : start + h * per] = block[..., order, :].reshape(*obs.shape[:-1], -1)
    return out


def _some_obs(env, tasks, n=6):
    obs = []
    for i in range(n):
        task = jax.tree_util.tree_map(lambda a, i=i: a[i], tasks)
        for t in (5, 30, 60):
            obs.append(np.asarray(env.observe(_state_at(env, task, t), task)))
    return np.stack(obs)


def test_attention_is_invariant_to_the_order_of_the_people():
    env, tasks, nets, params = _nets(observe_forecast=2, observe_sorted=False)
    obs = _some_obs(env, tasks)
    z = jnp.ones((obs.shape[0], nets.cfg.latent_dim))
    order = np.array([3, 0, 5, 1, 4, 2])
    a = nets.policy_out(params["policy"], obs, z)
    b = nets.policy_out(params["policy"], _permute(obs, nets, order), z)
    np.testing.assert_allclose(a[0], b[0], atol=1e-5)
    qa = nets.q_values(params["q"], obs, jnp.zeros((obs.shape[0], 2)), z)
    qb = nets.q_values(params["q"], _permute(obs, nets, order), jnp.zeros((obs.shape[0], 2)), z)
    np.testing.assert_allclose(qa, qb, atol=1e-5)
    # the MLP over fixed slots is not invariant: the test can tell
    flat = Networks(PearlConfig(hidden=(32, 32)), nets.obs_dim, 2)
    p0 = flat.init(jax.random.PRNGKey(0))["policy"]
    assert not np.allclose(
        flat.policy_out(p0, obs, z)[0], flat.policy_out(p0, _permute(obs, nets, order), z)[0]
    )


def test_absent_people_are_masked_out_and_an_empty_crowd_is_finite():
    env, tasks, nets, params = _nets(observe_forecast=2)
    obs = _some_obs(env, tasks)
    z = jnp.zeros((obs.shape[0], nets.cfg.latent_dim))
    parts = {n: (s, k) for n, s, k in nets.crowd.layout}
    ps, h = parts["people_present"][0], nets.crowd.num_people
    absent = obs[:, ps : ps + h] < 0
    assert absent.any() and (~absent).any()  # the sample has both
    noisy = np.array(obs)
    rng = np.random.default_rng(0)
    for start, per in _people_blocks(nets):
        if start == ps:
            continue
        block = noisy[:, start : start + h * per].reshape(-1, h, per)
        block[absent] = rng.uniform(-1, 1, size=block[absent].shape)
        noisy[:, start : start + h * per] = block.reshape(len(obs), -1)
    np.testing.assert_allclose(
        nets.policy_out(params["policy"], obs, z)[0],
        nets.policy_out(params["policy"], noisy, z)[0],
        atol=1e-5,
    )
    empty = np.array(obs)
    empty[:, ps : ps + h] = -1.0
    out = nets.policy_out(params["policy"], empty, z)
    assert np.isfinite(np.asarray(out[0])).all()

    def loss(p):
        return jnp.sum(nets.policy_out(p, empty, z)[0])

    grads = jax.grad(loss)(params["policy"])
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree_util.tree_leaves(grads))


def test_spec_round_trip_and_errors():
    env, tasks, nets, params = _nets(observe_forecast=2)
    spec = nets.spec()
    again = Networks.from_spec(spec)
    obs = _some_obs(env, tasks, 2)
    z = jnp.zeros((obs.shape[0], nets.cfg.latent_dim))
    np.testing.assert_array_equal(
        nets.act(params["policy"], obs, z, None), again.act(params["policy"], obs, z, None)
    )
    # without the encoder, the spec is what it was (no crowd entries)
    plain = Networks(PearlConfig(), 10, 2).spec()
    assert not {"crowd_encoder", "obs_layout"} & set(plain)
    assert Networks.from_spec(plain).crowd is None
    # one-line errors
    tasks_np = make_tasks("restaurant", "train", 0, config=_env().config)
    with pytest.raises(ConfigError, match="observe_presence=true"):
        e = _env()
        Networks(
            PearlConfig(crowd_encoder="attention"), e.obs_dim(tasks_np), 2, e.obs_layout(tasks_np)
        )
    with pytest.raises(ConfigError, match="needs the observation's layout"):
        Networks(PearlConfig(crowd_encoder="attention"), 10, 2)
    with pytest.raises(ConfigError, match="crowd_encoder"):
        PearlConfig(crowd_encoder="transformer")
    with pytest.raises(ConfigError, match="crowd_dim"):
        PearlConfig(crowd_encoder="attention", crowd_dim=30, crowd_heads=4)


def test_jitted_act_traces_once():
    env, tasks, nets, params = _nets()
    act = jax.jit(chex.assert_max_traces(lambda p, o, z: nets.act(p, o, z, None), n=1))
    obs = _some_obs(env, tasks, 2)
    z = jnp.zeros((obs.shape[0], nets.cfg.latent_dim))
    for _ in range(3):
        act(params["policy"], obs, z)


def _tiny_crowd_cfg():
    cfg = preset("smoke")
    return dataclasses.replace(
        cfg,
        pearl=cfg.pearl.replace(
            hidden=(16, 16),
            encoder_hidden=(16,),
            latent_dim=3,
            meta_batch=2,
            batch_size=16,
            context_size=8,
            crowd_encoder="attention",
            crowd_dim=8,
            crowd_heads=2,
        ),
        train=dataclasses.replace(
            cfg.train,
            eps=0.0,
            iterations=2,
            tasks_per_iteration=2,
            updates_per_iteration=2,
            eval_interval=0,
            rl_capacity=400,
        ),
        env_overrides={**EGO, "observe_presence": True, "observe_forecast": 2},
        task_options={"train_behaviours": 1},
    )


@pytest.mark.parametrize("kind", ["attention", "deepsets", "sarl", "none"])
def test_a_loaded_encoder_policy_acts_on_an_empty_batch(tmp_path, kind):
    """`load_policy` of a run with a crowd encoder: a batch of no observations gives no actions,
    shape (0, 2), from `act`, `__call__` and `jit()`'s act, as the MLP policy ("none") and the
    exported policy do (the entities' reshape inferred a size from the batch's 0 elements: a
    ZeroDivisionError). A batch of observations acts as the networks do."""
    from mpcpearl_jax import load_policy
    from mpcpearl_jax.runfolder import POLICY_FILE, save_config, save_network, save_params

    cfg = _tiny_crowd_cfg()
    cfg = dataclasses.replace(cfg, pearl=cfg.pearl.replace(crowd_encoder=kind))
    env = make_env(cfg.env, **cfg.env_overrides)
    tasks = make_tasks(cfg.env, "train", 0, config=env.config)
    nets = Networks(cfg.pearl, env.obs_dim(tasks), 2, env.obs_layout(tasks))
    params = nets.init(jax.random.PRNGKey(0))
    run = tmp_path / "run"
    save_config(run, cfg)
    save_network(run, nets)
    per_seed = {k: params[k] for k in ("policy", "encoder")}
    save_params(
        run / POLICY_FILE, jax.tree_util.tree_map(lambda x: jnp.stack([x] * cfg.seeds), per_seed)
    )
    policy = load_policy(run)
    assert (policy.nets.crowd is None) == (kind == "none")
    obs, z = jnp.zeros((0, policy.obs_dim)), jnp.zeros((0, policy.latent_dim))
    context = jnp.zeros((3, policy.context_dim))
    act, _ = policy.jit()
    assert policy.act(obs, z).shape == (0, 2)
    assert policy.act(obs, z, jax.random.PRNGKey(0)).shape == (0, 2)
    assert policy(obs, context).shape == (0, 2)
    assert act(obs, z).shape == (0, 2)
    none_of_two = jnp.zeros((2, 0, policy.obs_dim)), jnp.zeros((2, 0, policy.latent_dim))
    assert policy.act(*none_of_two).shape == (2, 0, 2)
    some = jnp.asarray(_some_obs(env, tasks, 2))
    zs = jnp.ones((len(some), policy.latent_dim))
    np.testing.assert_array_equal(policy.act(some, zs), nets.act(params["policy"], some, zs, None))


@pytest.mark.slow  # trains (~70 s); fast sibling: test_spec_round_trip_and_errors
def test_a_trained_crowd_policy_loads_and_exports(tmp_path):
    """A tiny training with the encoder: `load_policy` rebuilds it from the run folder alone and
    the exported artifact acts as it does."""
    from mpcpearl_jax import export_policy, load_exported, load_policy, train

    train(_tiny_crowd_cfg(), tmp_path / "run")
    policy = load_policy(tmp_path / "run")
    assert policy.nets.crowd is not None
    ex = load_exported(export_policy(tmp_path / "run", tmp_path / "policy.export"))
    rng = np.random.default_rng(0)
    obs = rng.uniform(-1, 1, (5, policy.obs_dim)).astype(np.float32)
    z = rng.normal(size=(5, policy.latent_dim)).astype(np.float32)
    act, _ = policy.jit()
    np.testing.assert_allclose(ex.act(obs, z), act(obs, z), atol=1e-6)


def test_a_run_without_the_observation_entries_fails_before_training(tmp_path):
    from mpcpearl_jax.config import validate

    cfg = _tiny_crowd_cfg()
    bad = dataclasses.replace(cfg, env_overrides=dict(EGO))
    with pytest.raises(ConfigError, match="env.observe_presence=true"):
        validate(bad)
