"""The cheap crowd encoders and the MPC as a teacher: `pearl.crowd_encoder` "deepsets",
`pearl.crowd_static` "flat", `pearl.crowd_shared` (one encoder for the critics, read by the
policy and V with stopped gradients) and `pearl.imitation` (the Q-filtered behaviour-cloning
term). Checked: a present person changes every encoder's output and one beyond the sensing
radius does not; invariance to the people's order; absent people not read; the shared encoder's
update against a NumPy-free reference built from the unshared losses' pieces (the heads on the
encoder's features are the networks on the observation; only the critics' loss moves the
encoder; the policy's and V's copies follow it; the target copy is its exponential average);
the imitation term against a NumPy reference, its Q-filter, and its weight 0 leaving the update
bit for bit as it was; the expert marks reaching the replay buffer; one trace per jitted step."""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.config import preset, validate
from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.envs.types import EnvState
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.pearl import Networks, Transitions, buffers, init_learner, make_update
from mpcpearl_jax.pearl.config import PearlConfig
from mpcpearl_jax.pearl.losses import make_losses
from mpcpearl_jax.pearl.networks import tanh_gaussian

EGO = dict(
    observe_relative=True,
    observe_velocity=True,
    observe_time=True,
    observe_presence=True,
    observe_forecast=2,
    sensing_radius=3.0,
)
# (crowd_encoder, crowd_static, crowd_shared[, crowd_layers])
KINDS = [
    ("attention", "pool", False),
    ("attention", "flat", True),
    ("deepsets", "pool", False),
    ("deepsets", "flat", True),
    ("sarl", "pool", False),
    ("sarl", "flat", True),
    ("sarl", "pool", True, 1),
    ("deepsets", "flat", True, 1),
]


def _env():
    return make_env("restaurant", **EGO)


def _nets(kind="deepsets", static="flat", shared=True, layers=2, **kw):
    env = _env()
    tasks = make_tasks("restaurant", "train", 0, config=env.config)
    cfg = PearlConfig(
        hidden=(32, 32),
        encoder_hidden=(16,),
        latent_dim=3,
        meta_batch=2,
        batch_size=24,
        context_size=8,
        crowd_encoder=kind,
        crowd_dim=16,
        crowd_heads=2,
        crowd_static=static,
        crowd_shared=shared,
        crowd_layers=layers,
        **kw,
    )
    return env, tasks, Networks(cfg, env.obs_dim(tasks), 2, env.obs_layout(tasks))


def _task_with_person_at(tasks, xy):
    """Training task 0 with person 0 standing at `xy` throughout (present) and the others
    absent."""
    task = jax.tree_util.tree_map(lambda a: a[0], tasks)
    pos = np.array(task.human_pos)
    mask = np.zeros(np.shape(task.human_mask), bool)
    pos[:, 0] = xy
    mask[:, 0] = True
    return task.replace(human_pos=jnp.asarray(pos), human_mask=jnp.asarray(mask))


@pytest.mark.parametrize("kind", KINDS)
def test_a_present_person_changes_the_output_one_beyond_the_sensing_radius_does_not(kind):
    env, tasks, nets = _nets(*kind)
    params = nets.init(jax.random.PRNGKey(1))
    task0 = jax.tree_util.tree_map(lambda a: a[0], tasks)
    robot = np.asarray(task0.start[:2], np.float64)
    state = EnvState(pose=task0.start.astype(jnp.float32), t=jnp.asarray(10, jnp.int32))
    away = robot / max(np.linalg.norm(robot), 1e-6)  # a direction; the arena is [-5, 5]^2

    def out(xy):
        obs = env.observe(state, _task_with_person_at(tasks, xy))[None]
        z = jnp.zeros((1, nets.cfg.latent_dim))
        mean = nets.policy_out(params["policy"], obs, z)[0]
        q = nets.q_values(params["q"], obs, jnp.zeros((1, 2)), z)
        return np.asarray(mean), np.asarray(q)

    near = out(robot + np.array([1.0, 0.5]))
    nearer = out(robot + np.array([0.4, -0.3]))
    far_a = out(robot - 3.6 * away)
    far_b = out(robot - 4.4 * away + np.array([0.0, 0.2]))
    assert np.linalg.norm(3.6 * away) > env.config.sensing_radius
    for i in range(2):  # policy mean and Q
        np.testing.assert_array_equal(far_a[i], far_b[i])  # beyond the radius: not seen
        assert np.max(np.abs(near[i] - far_a[i])) > 1e-6  # present: read
        assert np.max(np.abs(near[i] - nearer[i])) > 1e-6  # where it stands matters


def _permute(obs, nets, order):
    h = nets.crowd.num_people
    out = np.array(obs)
    for name, start, size in nets.crowd.layout:
        if name.startswith("people_"):
            per = size // h
            block = obs[..., start : start + size].reshape(*obs.shape[:-1], h, per)
            out[..., start : start + size] = block[..., order, :].reshape(*obs.shape[:-1], -1)
    return out


def _obs(env, tasks, n=4):
    out = []
    for i in range(n):
        task = jax.tree_util.tree_map(lambda a, i=i: a[i], tasks)
        for t in (5, 30, 60):
            state = EnvState(pose=task.start.astype(jnp.float32), t=jnp.asarray(t, jnp.int32))
            out.append(np.asarray(env.observe(state, task)))
    return np.stack(out)


@pytest.mark.parametrize("kind", KINDS)
def test_order_invariance_masking_and_an_empty_crowd(kind):
    env, tasks, nets = _nets(*kind)
    params = nets.init(jax.random.PRNGKey(0))
    obs = _obs(env, tasks)
    z = jnp.ones((len(obs), nets.cfg.latent_dim))
    order = np.array([3, 0, 5, 1, 4, 2])
    a = nets.policy_out(params["policy"], obs, z)[0]
    np.testing.assert_allclose(
        a, nets.policy_out(params["policy"], _permute(obs, nets, order), z)[0], atol=1e-5
    )
    parts = {n: (s, k) for n, s, k in nets.crowd.layout}
    ps, h = parts["people_present"][0], nets.crowd.num_people
    absent = obs[:, ps : ps + h] < 0
    assert absent.any() and (~absent).any()
    noisy = np.array(obs)
    rng = np.random.default_rng(0)
    for name, start, size in nets.crowd.layout:
        if name.startswith("people_") and name != "people_present":
            block = noisy[:, start : start + size].reshape(len(obs), h, -1)
            block[absent] = rng.uniform(-1, 1, size=block[absent].shape)
            noisy[:, start : start + size] = block.reshape(len(obs), -1)
    np.testing.assert_allclose(a, nets.policy_out(params["policy"], noisy, z)[0], atol=1e-5)
    empty = np.array(obs)
    empty[:, ps : ps + h] = -1.0
    grads = jax.grad(lambda p: jnp.sum(nets.policy_out(p, empty, z)[0]))(params["policy"])
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree_util.tree_leaves(grads))
    # an empty batch acts (shape (0, A))
    assert nets.act(params["policy"], obs[:0], z[:0], None).shape == (0, 2)


def _batch(nets, seed=0, expert_share=None):
    rng = np.random.default_rng(seed)
    mb, b, o = nets.cfg.meta_batch, nets.cfg.batch_size, nets.obs_dim
    f = lambda *s: jnp.asarray(rng.uniform(-1, 1, s), jnp.float32)  # noqa: E731
    expert = None
    if expert_share is not None:
        expert = jnp.asarray(rng.uniform(size=(mb, b)) < expert_share, jnp.float32)
    batch = Transitions(f(mb, b, o), f(mb, b, 2), f(mb, b), f(mb, b, o), jnp.zeros((mb, b)), expert)
    return batch, f(mb, nets.cfg.context_size, nets.context_dim)


def _leaves_equal(a, b):
    return all(
        np.array_equal(np.asarray(x), np.asarray(y))
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True)
    )


def test_the_shared_encoder_is_trained_by_the_critics_only_and_copied():
    env, tasks, nets = _nets("deepsets", "flat", True)
    state = init_learner(jax.random.PRNGKey(0), nets)
    p = state.params
    crowd = p["q"]["params"]["crowd"]
    # at init the policy, V and target V hold the critics' encoder
    assert _leaves_equal(p["policy"]["params"]["crowd"], crowd)
    assert _leaves_equal(p["v"]["params"]["crowd"], crowd)
    assert set(p["q"]["params"]) == {"crowd", "q1", "q2"}
    batch, ctx = _batch(nets)
    # the heads on the encoder's features are the networks on the observation
    zb = jnp.zeros(batch.obs.shape[:2] + (nets.cfg.latent_dim,))
    feats = nets.encode(p["q"], batch.obs)
    np.testing.assert_allclose(
        nets.q_heads(p["q"], feats, batch.action, zb),
        nets.q_values(p["q"], batch.obs, batch.action, zb),
        atol=1e-6,
    )
    np.testing.assert_allclose(
        nets.value_head(p["v"], feats, zb), nets.value(p["v"], batch.obs, zb), atol=1e-6
    )
    new, _ = make_update(nets)(state, batch, ctx, jax.random.PRNGKey(3))
    q_crowd = new.params["q"]["params"]["crowd"]
    assert not _leaves_equal(q_crowd, crowd)  # the critics' loss moved it
    # the critics' step alone, by the losses: the same encoder as the whole update's
    loss = make_losses(nets)
    k_z, _ = jax.random.split(jax.random.PRNGKey(3))
    q_enc = {"q": p["q"], "encoder": p["encoder"]}
    g = jax.grad(lambda qe: loss.critic_encoder(qe, state.target_v, batch, ctx, k_z)[0])(q_enc)
    assert any(
        np.abs(np.asarray(x)).max() > 0
        for x in jax.tree_util.tree_leaves(g["q"]["params"]["crowd"])
    )
    # the policy's and V's copies follow the critics'; the target copy is its average
    assert _leaves_equal(new.params["policy"]["params"]["crowd"], q_crowd)
    assert _leaves_equal(new.params["v"]["params"]["crowd"], q_crowd)
    tau = nets.cfg.tau
    for t_new, t_old, c in zip(
        jax.tree_util.tree_leaves(new.target_v["params"]["crowd"]),
        jax.tree_util.tree_leaves(state.target_v["params"]["crowd"]),
        jax.tree_util.tree_leaves(q_crowd),
        strict=True,
    ):
        np.testing.assert_allclose(
            t_new, tau * np.asarray(c) + (1 - tau) * np.asarray(t_old), atol=1e-6
        )
    # the policy's loss does not reach the encoder: its gradient there is 0
    x = jax.lax.stop_gradient(nets.encode(new.params["q"], batch.obs))
    gp = jax.grad(lambda pp: loss.policy(pp, new.params["q"], x, zb, jax.random.PRNGKey(4))[0])(
        new.params["policy"]
    )
    assert all(not np.any(np.asarray(v)) for v in jax.tree_util.tree_leaves(gp["params"]["crowd"]))


def test_jitted_update_traces_once():
    _, _, nets = _nets("deepsets", "flat", True, imitation=0.5)
    state = init_learner(jax.random.PRNGKey(0), nets)
    update = jax.jit(chex.assert_max_traces(make_update(nets, jit=False), n=1))
    batch, ctx = _batch(nets, expert_share=0.3)
    for i in range(3):
        state, m = update(state, batch, ctx, jax.random.PRNGKey(i))
    assert np.isfinite(float(m["bc_loss"])) and 0 <= float(m["bc_kept"]) <= 1


def _bc_reference(mean, min_q, q_expert, mark, a_e):
    keep = mark * (q_expert >= min_q)
    err = np.sum((np.tanh(mean) - a_e) ** 2, axis=-1)
    n = max(mark.sum(), 1.0)
    return float(np.sum(keep * err) / n), float(keep.sum() / n)


@pytest.mark.parametrize("shared", [False, True])
def test_imitation_term_matches_a_numpy_reference(shared):
    _, _, nets = _nets("deepsets", "flat", shared, imitation=2.0)
    state = init_learner(jax.random.PRNGKey(0), nets)
    p = state.params
    batch, _ = _batch(nets, seed=1, expert_share=0.4)
    loss = make_losses(nets)
    zb = jnp.asarray(np.random.default_rng(2).normal(size=batch.obs.shape[:2] + (3,)), jnp.float32)
    x = nets.encode(p["q"], batch.obs) if shared else batch.obs
    key = jax.random.PRNGKey(5)
    with_bc, aux = loss.policy(p["policy"], p["q"], x, zb, key, None, (batch.expert, batch.action))
    without, _ = loss.policy(p["policy"], p["q"], x, zb, key, None, None)
    mean = np.asarray(nets.policy_out(p["policy"], batch.obs, zb)[0])
    q1, q2 = nets.q_values(p["q"], batch.obs, batch.action, zb)
    q_expert = np.minimum(np.asarray(q1), np.asarray(q2))
    # the policy's sample, drawn as the loss draws it
    mu, log_std = nets.policy_out(p["policy"], batch.obs, zb)
    a_pi = tanh_gaussian(mu, log_std).sample(seed=key)
    min_q = np.minimum(*(np.asarray(q) for q in nets.q_values(p["q"], batch.obs, a_pi, zb)))
    bc, kept = _bc_reference(
        mean, min_q, q_expert, np.asarray(batch.expert), np.asarray(batch.action)
    )
    assert 0 < kept < 1  # the filter keeps some and drops some: it is tested both ways
    np.testing.assert_allclose(float(aux["bc_loss"]), bc, rtol=1e-4)
    np.testing.assert_allclose(float(aux["bc_kept"]), kept, rtol=1e-5)
    q_scale = np.mean(np.abs(min_q))
    np.testing.assert_allclose(
        float(with_bc) - float(without), 2.0 * q_scale * bc, rtol=1e-4, atol=1e-5
    )
    # no MPC transition in the batch: no term
    none = jnp.zeros_like(batch.expert)
    l_none, aux_none = loss.policy(p["policy"], p["q"], x, zb, key, None, (none, batch.action))
    assert float(aux_none["bc_loss"]) == 0.0 and float(l_none) == float(without)


def test_imitation_off_leaves_the_update_as_it_was():
    """Weight 0 (every preset): the same update bit for bit, marks in the batch or not."""
    _, _, nets = _nets("deepsets", "flat", True)
    state = init_learner(jax.random.PRNGKey(0), nets)
    batch, ctx = _batch(nets, seed=3)
    marked = batch._replace(expert=jnp.ones(batch.reward.shape))
    a, _ = make_update(nets)(state, batch, ctx, jax.random.PRNGKey(1))
    b, _ = make_update(nets)(state, marked, ctx, jax.random.PRNGKey(1))
    assert _leaves_equal(a.params, b.params)
    _, _, imit = _nets("deepsets", "flat", True, imitation=1.0)
    with pytest.raises(ValueError, match="expert marks"):
        make_update(imit)(
            init_learner(jax.random.PRNGKey(0), imit), batch, ctx, jax.random.PRNGKey(1)
        )


def test_buffers_keep_the_expert_marks():
    buf = buffers.init_buffer(3, 5, 4, 2, expert=True)
    data = Transitions(
        jnp.ones((1, 4, 4)),
        jnp.ones((1, 4, 2)),
        jnp.ones((1, 4)),
        jnp.ones((1, 4, 4)),
        jnp.zeros((1, 4)),
        jnp.asarray([[1.0, 0.0, 1.0, 0.0]]),
    )
    buf = buffers.insert(buf, jnp.asarray([1]), data)
    np.testing.assert_array_equal(buf.data.expert[1, :4], [1, 0, 1, 0])
    plain = buffers.init_buffer(3, 5, 4, 2)
    assert plain.data.expert is None and len(jax.tree_util.tree_leaves(plain.data)) == 5


def test_config_errors_name_the_field():
    with pytest.raises(ConfigError, match="crowd_static"):
        PearlConfig(crowd_static="grid")
    with pytest.raises(ConfigError, match="crowd_shared"):
        PearlConfig(crowd_shared="yes")
    with pytest.raises(ConfigError, match="imitation"):
        PearlConfig(imitation=-1.0)
    with pytest.raises(ConfigError, match="crowd_layers"):
        PearlConfig(crowd_layers=0)
    PearlConfig(crowd_encoder="deepsets", crowd_dim=30)  # heads only matter for attention
    cfg = preset("default")
    bad = dataclasses.replace(
        cfg, pearl=cfg.pearl.replace(imitation=1.0), train=dataclasses.replace(cfg.train, eps=0.0)
    )
    with pytest.raises(ConfigError, match="PearlConfig.imitation.*train.eps"):
        validate(bad)


def test_spec_round_trip_keeps_the_encoder_kind():
    env, tasks, nets = _nets("deepsets", "flat", True)
    params = nets.init(jax.random.PRNGKey(0))
    again = Networks.from_spec(nets.spec())
    assert again.crowd == nets.crowd and again.shared
    obs = _obs(env, tasks, 2)
    z = jnp.zeros((len(obs), 3))
    np.testing.assert_array_equal(
        nets.act(params["policy"], obs, z, None), again.act(params["policy"], obs, z, None)
    )
