"""The learner extensions of docs/extensions.md: the MPC as a guide policy (`train.guide_share`),
the kept policy (`train.keep_best`), n-step returns (`pearl.n_step`) and CrossQ critics
(`pearl.crossq`); each off in every preset, each checked against a NumPy reference or by the
property it promises."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.config import PRESETS, TrainConfig
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.pearl import buffers
from mpcpearl_jax.pearl.config import PearlConfig
from mpcpearl_jax.pearl.types import Transitions


def test_every_preset_leaves_the_learner_extensions_off():
    for name, cfg in PRESETS.items():
        assert cfg.train.guide_share == 0 and not cfg.train.keep_best, name
        assert cfg.pearl.n_step == 1 and not cfg.pearl.crossq, name


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: TrainConfig(guide_share=0.5, eps=0.0), "guide_share"),
        (lambda: TrainConfig(guide_share=1.0), "guide_share"),
        (lambda: TrainConfig(guide_share=-0.1), "guide_share"),
        (lambda: TrainConfig(guide_share=0.5, posterior_episodes=0), "guide_share"),
        (lambda: TrainConfig(guide_steps=0), "guide_steps"),
        (lambda: TrainConfig(guide_decrement=-1), "guide_decrement"),
        (lambda: TrainConfig(guide_success=1.5), "guide_success"),
        (lambda: TrainConfig(keep_best=1), "keep_best"),
        (lambda: TrainConfig(keep_interval=0), "keep_interval"),
        (lambda: TrainConfig(keep_tasks=0), "keep_tasks"),
        (lambda: PearlConfig(n_step=0), "n_step"),
        (lambda: PearlConfig(n_step=2.5), "n_step"),
        (lambda: PearlConfig(crossq=True, layer_norm=True), "crossq"),
        (lambda: PearlConfig(crossq=1), "crossq"),
        (lambda: PearlConfig(crossq=True, crossq_momentum=1.5), "crossq_momentum"),
    ],
)
def test_bad_extension_settings_name_their_field(make, field):
    with pytest.raises(ConfigError, match=field):
        make()


# ------------------------------------------------------------------------------ n-step returns
def _episode_buffer(num_tasks=2, capacity=12, horizon=4, filled=12, obs_dim=3):
    """A replay buffer of whole episodes with distinct rewards and observations per row."""
    buf = buffers.init_buffer(num_tasks, capacity, obs_dim, 2)
    rng = np.random.default_rng(0)
    n = filled
    data = Transitions(
        jnp.asarray(rng.normal(size=(num_tasks, n, obs_dim)), jnp.float32),
        jnp.asarray(rng.normal(size=(num_tasks, n, 2)), jnp.float32),
        jnp.asarray(rng.normal(size=(num_tasks, n)), jnp.float32),
        jnp.asarray(rng.normal(size=(num_tasks, n, obs_dim)), jnp.float32),
        jnp.zeros((num_tasks, n)),
    )
    return buffers.insert(buf, jnp.arange(num_tasks), data), data


@pytest.mark.parametrize("steps, filled", [(3, 12), (3, 8), (1, 12), (5, 12)])
def test_n_step_sample_matches_a_numpy_reference(steps, filled):
    horizon, gamma, n = 4, 0.9, 64
    buf, data = _episode_buffer(filled=filled, horizon=horizon)
    key, tids = jax.random.PRNGKey(3), jnp.array([1, 0])
    got = buffers.sample_n_step(buf, key, tids, n, steps, gamma, horizon)
    one = buffers.sample(buf, key, tids, n)  # the same start rows
    idx = np.asarray(jax.random.randint(key, (2, n), 0, np.asarray(buf.size)[tids][:, None]))
    rew, nobs = np.asarray(data.reward), np.asarray(data.next_obs)
    for i, task in enumerate(np.asarray(tids)):
        for b in range(n):
            t = idx[i, b]
            m = min(steps, horizon - t % horizon)
            ref = sum(gamma**j * rew[task, t + j] for j in range(m))
            np.testing.assert_allclose(got.reward[i, b], ref, rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(got.next_obs[i, b], nobs[task, t + m - 1], rtol=1e-6)
            np.testing.assert_allclose(got.discount[i, b], gamma**m, rtol=1e-6)
    np.testing.assert_array_equal(got.obs, one.obs)
    np.testing.assert_array_equal(got.action, one.action)


def test_one_step_batches_give_the_papers_critic_loss():
    """n_step = 1 through the n-step path (discount gamma) equals the paper's target exactly,
    and a longer n changes it."""
    from mpcpearl_jax.pearl.losses import make_losses
    from mpcpearl_jax.pearl.networks import Networks

    cfg = PearlConfig(hidden=(8,), encoder_hidden=(8,), latent_dim=2, gamma=0.9)
    nets = Networks(cfg, 3, 2)
    params = nets.init(jax.random.PRNGKey(0))
    buf, _ = _episode_buffer()
    tids = jnp.array([0, 1])
    plain = buffers.sample(buf, jax.random.PRNGKey(1), tids, 16)
    n1 = buffers.sample_n_step(buf, jax.random.PRNGKey(1), tids, 16, 1, 0.9, 4)
    n3 = buffers.sample_n_step(buf, jax.random.PRNGKey(1), tids, 16, 3, 0.9, 4)
    ctx = jnp.concatenate([plain.obs, plain.action, plain.reward[..., None], plain.next_obs], -1)
    loss = make_losses(nets).critic_encoder
    q_enc = {"q": params["q"], "encoder": params["encoder"]}
    k = jax.random.PRNGKey(2)
    ref = loss(q_enc, params["v"], plain, ctx, k)[0]
    np.testing.assert_allclose(loss(q_enc, params["v"], n1, ctx, k)[0], ref, rtol=1e-6)
    assert abs(float(loss(q_enc, params["v"], n3, ctx, k)[0]) - float(ref)) > 1e-6


def test_n_step_needs_whole_episodes_in_the_replay_buffer():
    from mpcpearl_jax.training.trainer import Trainer
    from tests.test_training import TINY

    bad = TINY.replace(pearl=TINY.pearl.replace(n_step=3))
    bad = bad.replace(train=dataclasses.replace(bad.train, rl_capacity=401))
    with pytest.raises(ConfigError, match="n_step.*rl_capacity"):
        Trainer(bad)


# ---------------------------------------------------------------------------- the MPC as guide
def test_the_guide_acts_on_every_step_before_the_hand_over_and_never_after():
    """A stand-in MPC marks its steps: with events switched off (eps so small no draw fires),
    exactly the steps t < handover of each row are the MPC's."""
    from mpcpearl_jax.envs import make_env, tasks_for
    from mpcpearl_jax.pearl.networks import Networks
    from mpcpearl_jax.training.collect import make_collector, rows_of
    from tests.test_training import TINY

    env = make_env("restaurant")
    tasks = tasks_for(TINY, "train", config=env.config)
    nets = Networks(TINY.pearl, env.obs_dim(tasks), env.action_dim)

    def bridge(key, fire, state, flat, a_pi, stamp):
        return jnp.full_like(a_pi, 0.25), fire, None

    collect = make_collector(env, nets, bridge, eps=1e-12)
    params = jax.vmap(nets.init)(jax.random.split(jax.random.PRNGKey(0), 1))["policy"]
    rows = rows_of(tasks, jnp.array([[0, 1, 2, 3]]))
    z = jnp.zeros((1, 4, TINY.pearl.latent_dim))
    handover = jnp.array([[0, 5, 17, env.config.horizon]], jnp.int32)
    ep = collect(jax.random.PRNGKey(1), params, z, rows, None, handover)
    t = np.arange(env.config.horizon)
    for r, h in enumerate(np.asarray(handover[0])):
        np.testing.assert_array_equal(np.asarray(ep.used_mpc[0, r]), t < h)
        acted = np.all(np.asarray(ep.transitions.action[0, r]) == 0.25, -1)
        np.testing.assert_array_equal(acted[:h], True)


def _guided_trainer(**changes):
    from mpcpearl_jax.training.trainer import Trainer
    from tests.test_training import TINY

    base = dict(eps=0.2, guide_share=0.5, guide_steps=30, guide_decrement=8)
    tc = dataclasses.replace(TINY.train, **{**base, **changes})
    return Trainer(TINY.replace(train=tc, mpc={"unsafe_recovery": True, "n_workers": 1}))


def test_the_roll_in_bound_shrinks_only_after_guided_success():
    tr = _guided_trainer(guide_success=0.5)
    state = tr.init_state()
    assert np.asarray(state.guide_h).tolist() == [30, 30]
    post = {"guide_rows": jnp.array([0.5, 0.0]), "guide_success": jnp.array([0.5, 1.0])}
    state = tr._shrink_roll_in(state, post)  # seed 1 had no guided row: keeps its bound
    assert np.asarray(state.guide_h).tolist() == [22, 30]
    post = {"guide_rows": jnp.array([0.5, 0.5]), "guide_success": jnp.array([0.25, 0.5])}
    for _ in range(5):
        state = tr._shrink_roll_in(state, post)
    assert np.asarray(state.guide_h).tolist() == [22, 0]  # never below 0
    tr.close()


def test_guided_rows_are_drawn_from_the_policy_rows_and_kept_out_of_its_success_rate():
    # no event draw fires (eps tiny): the MPC solves only the few guided steps
    tr = _guided_trainer(explore_start_share=0.5, guide_steps=4, eps=1e-9)
    state = tr.init_state()
    ids = jnp.array([[0, 1], [2, 3]])
    state, _ = tr.prior_collection(state, ids)  # the context of the posterior phase
    state, stats = tr.posterior_collection(state, ids)
    assert set(stats) >= {"guide_rows", "guide_success", "explore_rows", "success"}
    assert np.all(np.asarray(stats["guide_rows"]) + np.asarray(stats["explore_rows"]) <= 1.0)
    tr.close()


# --------------------------------------------------------------------------- the kept policy
def test_the_kept_policy_changes_only_for_a_better_score_and_is_what_the_run_reports():
    from mpcpearl_jax.training.run import policy_params
    from mpcpearl_jax.training.trainer import Trainer, reported_params
    from tests.test_training import TINY

    tr = Trainer(TINY.replace(train=dataclasses.replace(TINY.train, keep_best=True, keep_tasks=3)))
    state = tr.init_state()
    state, _ = tr.initial_collection(state)
    state, log = tr.keep_best(state)  # anything beats the initial -inf score
    assert log["kept_replaced"] == 1.0
    current = lambda s: s.learner.params["policy"]  # noqa: E731
    same = lambda a, b: all(  # noqa: E731
        bool(jnp.all(x == y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )
    assert same(state.kept["policy"], current(state))
    state, _ = tr.update_phase(state)  # the learner moves on
    assert not same(state.kept["policy"], current(state))
    kept_before = state.kept
    state = state.replace(kept_score=jnp.full_like(state.kept_score, jnp.inf))
    state, log = tr.keep_best(state)  # nothing beats +inf: the kept policy stays
    assert log["kept_replaced"] == 0.0 and same(state.kept, kept_before)
    assert same(reported_params(state), kept_before)
    assert same(policy_params(state), jax.device_get(kept_before))
    # the evaluation scores the kept policy, not the current one
    ev = tr.evaluate(state, tasks=jax.tree.map(lambda x: x[:2], tr.test_tasks))
    ref = tr.evaluate_adapt(jax.random.PRNGKey(12345), kept_before, tr.test_tasks)
    assert ev["return"] == pytest.approx(float(np.mean(np.asarray(ref["return"])[:, :2])), rel=1e-5)
    tr.close()


def test_a_checkpoint_holds_the_extension_state_and_restores_it_exactly(tmp_path):
    from mpcpearl_jax.training.checkpoint import Checkpointer
    from mpcpearl_jax.training.run import policy_params

    tr = _guided_trainer(keep_best=True, keep_tasks=2)
    state = tr.init_state()
    state, _ = tr.update_phase(state)  # parameters that differ from a fresh state's
    state, _ = tr.keep_best(state)
    state = state.replace(guide_h=jnp.array([22, 14], jnp.int32), iteration=state.iteration + 1)
    ck = Checkpointer(tmp_path, keep=2)
    ck.save(1, state, policy_params(state))
    back = ck.restore(template=tr.init_state())
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.asarray(back.guide_h).tolist() == [22, 14]
    ck.close()
    tr.close()


# ----------------------------------------------------------------------------- CrossQ critics
def _np_batchnorm_mlp(p, x, stats=None, eps=1e-5):
    """NumPy forward of `BatchNormMLP` with the batch's statistics over every leading axis
    (stats None) or the given running ones; returns (out, batch means, batch variances)."""
    means, variances = [], []
    n_dense = sum(k.startswith("Dense") for k in p)

    def norm(y, i):
        axes = tuple(range(y.ndim - 1))
        if stats is None:
            m, v = y.mean(axes), y.var(axes)
        else:
            m, v = np.asarray(stats[f"BatchNorm_{i}"]["mean"]), stats[f"BatchNorm_{i}"]["var"]
        means.append(y.mean(axes))
        variances.append(y.var(axes))
        bn = p[f"BatchNorm_{i}"]
        return (y - m) / np.sqrt(np.asarray(v) + eps) * np.asarray(bn["scale"]) + np.asarray(
            bn["bias"]
        )

    x = norm(np.asarray(x, np.float64), 0)
    for i in range(n_dense - 1):
        d = p[f"Dense_{i}"]
        x = np.maximum(x @ np.asarray(d["kernel"]) + np.asarray(d["bias"]), 0.0)
        x = norm(x, i + 1)
    d = p[f"Dense_{n_dense - 1}"]
    return x @ np.asarray(d["kernel"]) + np.asarray(d["bias"]), means, variances


def _crossq_setup(gamma=0.9, momentum=0.99):
    from mpcpearl_jax.pearl.networks import Networks

    cfg = PearlConfig(
        hidden=(8, 8),
        encoder_hidden=(8,),
        latent_dim=2,
        gamma=gamma,
        reward_scale=5.0,
        crossq=True,
        crossq_momentum=momentum,
    )
    nets = Networks(cfg, 3, 2)
    params = nets.init(jax.random.PRNGKey(0))
    buf, _ = _episode_buffer()
    batch = buffers.sample(buf, jax.random.PRNGKey(1), jnp.array([0, 1]), 16)
    ctx = jnp.concatenate([batch.obs, batch.action, batch.reward[..., None], batch.next_obs], -1)
    return nets, params, batch, ctx


@pytest.mark.parametrize("alpha", [None, 0.3])
def test_crossq_critic_loss_matches_a_numpy_reference(alpha):
    """L_psi against r_scale c + gamma (min Q(s', a') - alpha log pi(a'|s')), the two halves
    normalised together with the joint batch's statistics; running statistics updated with the
    momentum."""
    from mpcpearl_jax.pearl.losses import make_losses
    from mpcpearl_jax.pearl.networks import tanh_gaussian

    nets, params, batch, ctx = _crossq_setup()
    q_enc = {"q": params["q"], "encoder": params["encoder"]}
    key = jax.random.PRNGKey(2)
    a = None if alpha is None else jnp.asarray(alpha)
    loss, aux = make_losses(nets).critic_encoder_crossq(q_enc, params["policy"], batch, ctx, key, a)
    # the same draws as the loss: z from k_z, a' from k_next
    k_z, k_next = jax.random.split(key)
    z = nets.posterior_sample(params["encoder"], ctx, k_z)[0]
    zb = np.broadcast_to(np.asarray(z)[:, None, :], (2, 16, 2))
    mean_n, log_std_n = nets.policy_out(params["policy"], batch.next_obs, jnp.asarray(zb))
    a_next, logp = tanh_gaussian(mean_n, log_std_n).sample_and_log_prob(seed=k_next)
    x = np.concatenate(
        [
            np.concatenate([batch.obs, batch.action, zb], -1),
            np.concatenate([batch.next_obs, a_next, zb], -1),
        ],
        axis=1,
    )
    qp = params["q"]["params"]
    q1, m1, v1 = _np_batchnorm_mlp(qp["q1"], x)
    q2 = _np_batchnorm_mlp(qp["q2"], x)[0]
    q1, q2 = q1[..., 0], q2[..., 0]
    w = 1.0 if alpha is None else alpha
    target = 5.0 * np.asarray(batch.reward) + 0.9 * (
        np.minimum(q1[:, 16:], q2[:, 16:]) - w * np.asarray(logp)
    )
    q_loss = np.mean((q1[:, :16] - target) ** 2) + np.mean((q2[:, :16] - target) ** 2)
    np.testing.assert_allclose(aux["q_loss"], q_loss, rtol=2e-4, atol=1e-7)
    stats = aux["stats"]["batch_stats"]["q1"]
    for i, (m, v) in enumerate(zip(m1, v1, strict=True)):  # from mean 0, variance 1
        np.testing.assert_allclose(stats[f"BatchNorm_{i}"]["mean"], 0.01 * m, rtol=1e-3, atol=1e-7)
        np.testing.assert_allclose(
            stats[f"BatchNorm_{i}"]["var"], 0.99 + 0.01 * v, rtol=1e-4, atol=1e-7
        )


def test_crossq_update_trains_q_with_running_statistics_and_leaves_v_alone():
    """Over jitted steps (traced once): the Q weights and running statistics move, V and its
    target stay as initialised, and the policy loss reads Q with the running statistics."""
    import chex

    from mpcpearl_jax.pearl.learner import init_learner, make_update

    nets, _, batch, ctx = _crossq_setup()
    state = init_learner(jax.random.PRNGKey(0), nets)
    start = state
    update = chex.assert_max_traces(make_update(nets, jit=False), n=1)
    step = jax.jit(update)
    for i in range(3):
        state, metrics = step(state, batch, ctx, jax.random.PRNGKey(10 + i))
    assert int(state.steps) == 3 and float(metrics["v_loss"]) == 0.0
    for part in ("v", "target_v"):
        before = start.params["v"] if part == "v" else start.target_v
        after = state.params["v"] if part == "v" else state.target_v
        for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(after), strict=True):
            np.testing.assert_array_equal(a, b)
    old, new = start.params["q"], state.params["q"]
    w0, w1 = (q["params"]["q1"]["Dense_0"]["kernel"] for q in (old, new))
    m0, m1 = (q["batch_stats"]["q1"]["BatchNorm_0"]["mean"] for q in (old, new))
    assert not np.allclose(w0, w1) and not np.allclose(m0, m1)
    # running statistics: Q in evaluation mode is the NumPy forward with those statistics
    x = np.concatenate([batch.obs, batch.action, np.zeros((2, 16, 2))], -1)
    q1 = nets.q_values(new, batch.obs, batch.action, jnp.zeros((2, 16, 2)))[0]
    ref = _np_batchnorm_mlp(new["params"]["q1"], x, new["batch_stats"]["q1"])[0][..., 0]
    np.testing.assert_allclose(q1, ref, rtol=2e-4, atol=1e-6)


def test_crossq_networks_round_trip_through_their_spec():
    from mpcpearl_jax.pearl.networks import Networks

    nets = _crossq_setup(momentum=0.9)[0]
    back = Networks.from_spec(nets.spec())
    assert back.cfg.crossq and back.cfg.crossq_momentum == 0.9
    assert "crossq" not in Networks(PearlConfig(), 3, 2).spec()  # absent where it is off


def test_crossq_trains_and_checkpoints_exactly(tmp_path):
    """A trainer with CrossQ critics runs an update phase and restores bit for bit."""
    from mpcpearl_jax.training.checkpoint import Checkpointer
    from mpcpearl_jax.training.run import policy_params
    from mpcpearl_jax.training.trainer import Trainer
    from tests.test_training import TINY

    tr = Trainer(TINY.replace(pearl=TINY.pearl.replace(crossq=True)))
    state = tr.init_state()
    state, metrics = tr.update_phase(state)
    assert "batch_stats" in state.learner.params["q"]
    assert np.isfinite(float(np.mean(np.asarray(metrics["q_loss"]))))
    state = state.replace(iteration=state.iteration + 1)  # a checkpoint holds its iteration
    ck = Checkpointer(tmp_path, keep=2)
    ck.save(1, state, policy_params(state))
    back = ck.restore(template=tr.init_state())
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    ck.close()
    tr.close()


def test_the_final_policy_of_a_kept_run_is_written_for_evaluation(tmp_path, capsys):
    """experiments.diagnostics.final_policy writes the learner's own {policy, encoder} of the
    newest checkpoint (not the kept one), with the run's config and network files."""
    from flax import serialization

    from experiments.diagnostics import final_policy
    from mpcpearl_jax.pearl.learner import acting_params
    from mpcpearl_jax.training.checkpoint import Checkpointer, save_config, save_network
    from mpcpearl_jax.training.run import policy_params

    tr = _guided_trainer(keep_best=True, keep_tasks=2, guide_share=0.0)
    state = tr.init_state()
    state, _ = tr.keep_best(state)  # kept = the fresh policy
    state, _ = tr.update_phase(state)  # the learner moves on
    state = state.replace(iteration=state.iteration + 1)
    run, work = tmp_path / "run", tmp_path / "work"
    save_config(run, tr.cfg)
    save_network(run, tr.nets)
    ck = Checkpointer(work, keep=2)
    ck.save(1, state, policy_params(state))
    ck.close()
    tr.close()
    assert final_policy.main([str(run), str(work), "--out", str(tmp_path / "final")]) == 0
    want = jax.device_get(acting_params(state.learner.params))
    got = serialization.from_bytes(want, (tmp_path / "final/policy.msgpack").read_bytes())
    for a, b in zip(jax.tree.leaves(want), jax.tree.leaves(got), strict=True):
        np.testing.assert_array_equal(a, b)
    kept = jax.tree.leaves(jax.device_get(state.kept))
    assert any(not np.array_equal(a, b) for a, b in zip(kept, jax.tree.leaves(got), strict=True))
    assert (tmp_path / "final/network.json").exists() and (tmp_path / "final/config.json").exists()
    save_config(run, tr.cfg.replace(train=dataclasses.replace(tr.cfg.train, keep_best=False)))
    assert final_policy.main([str(run), str(work), "--out", str(tmp_path / "x")]) == 2
    assert "not a keep_best run" in capsys.readouterr().err
