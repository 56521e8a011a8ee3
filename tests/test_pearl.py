"""PEARL networks and losses: posterior, KL, log-probs, gradient routing (method §7)."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.pearl import (
    PearlConfig,
    Transitions,
    init_learner,
    losses,
    make_update,
    target_entropy,
)
from mpcpearl_jax.pearl.networks import (
    Networks,
    kl_to_standard_normal,
    product_of_gaussians,
    tanh_gaussian,
)

SMALL = PearlConfig(
    hidden=(32, 32),
    encoder_hidden=(16, 16),
    latent_dim=3,
    meta_batch=2,
    batch_size=8,
    context_size=5,
)
OBS, A = 7, 2


def _batch(key, cfg=SMALL):
    k = jax.random.split(key, 4)
    mb, b = cfg.meta_batch, cfg.batch_size
    return Transitions(
        jax.random.normal(k[0], (mb, b, OBS)),
        jnp.tanh(jax.random.normal(k[1], (mb, b, A))),
        jax.random.normal(k[2], (mb, b)),
        jax.random.normal(k[3], (mb, b, OBS)),
        jnp.zeros((mb, b)),
    )


def _context(key, cfg=SMALL):
    return jax.random.normal(key, (cfg.meta_batch, cfg.context_size, 2 * OBS + A + 1))


def test_product_of_gaussians_matches_numpy():
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(3, 6, 4)).astype(np.float32)
    var = rng.uniform(0.1, 2.0, size=(3, 6, 4)).astype(np.float32)
    mask = (rng.uniform(size=(3, 6)) > 0.3).astype(np.float32)
    mask[:, 0] = 1.0
    m, v = product_of_gaussians(jnp.asarray(mean), jnp.asarray(var), jnp.asarray(mask))
    prec = mask[..., None] / var
    v_ref = 1.0 / prec.sum(1)
    m_ref = v_ref * (mean * prec).sum(1)
    np.testing.assert_allclose(v, v_ref, rtol=1e-5)
    np.testing.assert_allclose(m, m_ref, rtol=1e-4, atol=1e-5)
    # unmasked = all ones
    m2, v2 = product_of_gaussians(jnp.asarray(mean), jnp.asarray(var))
    np.testing.assert_allclose(v2, 1.0 / (1.0 / var).sum(1), rtol=1e-5)


def test_kl_to_standard_normal_matches_numpy():
    rng = np.random.default_rng(1)
    mean = rng.normal(size=(5, 4))
    var = rng.uniform(0.05, 3.0, size=(5, 4))
    kl_ref = 0.5 * np.sum(var + mean**2 - 1.0 - np.log(var), axis=-1)
    np.testing.assert_allclose(
        kl_to_standard_normal(jnp.asarray(mean), jnp.asarray(var)), kl_ref, rtol=1e-5
    )
    assert float(kl_to_standard_normal(jnp.zeros(4), jnp.ones(4))) == pytest.approx(0.0)


def test_tanh_gaussian_logprob_finite_at_bounds():
    # huge means push the pre-tanh sample far out: tanh saturates at +-1 in float32
    mean = jnp.array([[40.0, -40.0], [0.0, 0.0], [15.0, -15.0]])
    log_std = jnp.array([[2.0, 2.0], [-20.0, -20.0], [-5.0, 0.0]])
    a, logp = tanh_gaussian(mean, log_std).sample_and_log_prob(seed=jax.random.PRNGKey(0))
    assert jnp.all(jnp.isfinite(logp)), logp
    assert jnp.all(jnp.abs(a) <= 1.0)
    # and against the analytic formula where it is well conditioned
    d = tanh_gaussian(jnp.zeros(2), jnp.zeros(2))
    x, lp = d.sample_and_log_prob(seed=jax.random.PRNGKey(3))
    pre = jnp.arctanh(x)
    ref = jnp.sum(jax.scipy.stats.norm.logpdf(pre) - jnp.log1p(-(x**2)))
    assert float(lp) == pytest.approx(float(ref), rel=1e-4, abs=1e-4)


def _nonzero(tree):
    return any(bool(jnp.any(g != 0)) for g in jax.tree_util.tree_leaves(tree))


def test_gradients_reach_exactly_the_right_parameters():
    nets = Networks(SMALL, OBS, A)
    params = nets.init(jax.random.PRNGKey(0))
    batch, ctx = _batch(jax.random.PRNGKey(1)), _context(jax.random.PRNGKey(2))
    key = jax.random.PRNGKey(3)
    loss = losses.make_losses(nets)  # SMALL: the paper's gamma, reward scale, KL weight
    # critic + KL: gradients into Q and the encoder, none into the target V
    q_enc = {"q": params["q"], "encoder": params["encoder"]}
    # each gradient is jitted: one compile instead of one per operation (~30 s eagerly)
    g = jax.jit(
        jax.grad(lambda qe, tv: loss.critic_encoder(qe, tv, batch, ctx, key)[0], argnums=(0, 1))
    )(q_enc, params["v"])
    assert _nonzero(g[0]["q"]) and _nonzero(g[0]["encoder"])
    assert not _nonzero(g[1])
    # policy loss: no gradient into Q params or the encoder (z detached)
    z = nets.sample_z(params["encoder"], ctx, key)
    zb = jnp.broadcast_to(z[:, None], batch.obs.shape[:2] + z.shape[-1:])

    def pol(p_pi, p_q, p_enc):
        zz = nets.sample_z(p_enc, ctx, key)
        zz = jnp.broadcast_to(jax.lax.stop_gradient(zz)[:, None], zb.shape)
        return loss.policy(p_pi, jax.lax.stop_gradient(p_q), batch.obs, zz, key)[0]

    gp = jax.jit(jax.grad(pol, argnums=(0, 1, 2)))(params["policy"], params["q"], params["encoder"])
    assert _nonzero(gp[0]) and not _nonzero(gp[1]) and not _nonzero(gp[2])
    # value loss: only V (the target is a constant)
    target = jax.random.normal(jax.random.PRNGKey(4), zb.shape[:2])
    gv = jax.jit(jax.grad(lambda pv, tgt: loss.value(pv, batch.obs, zb, tgt), argnums=(0, 1)))(
        params["v"], target
    )
    assert _nonzero(gv[0]) and not _nonzero(gv[1])


def test_update_changes_params_and_respects_detach():
    """One full update: policy and V change; the encoder changes only through Q + KL."""
    nets = Networks(SMALL, OBS, A)
    state = init_learner(jax.random.PRNGKey(0), nets)
    update = make_update(nets)
    new, m = update(
        state, _batch(jax.random.PRNGKey(1)), _context(jax.random.PRNGKey(2)), jax.random.PRNGKey(3)
    )
    for name in ("policy", "q", "v", "encoder"):
        diff = jax.tree_util.tree_map(
            lambda a, b: jnp.max(jnp.abs(a - b)), new.params[name], state.params[name]
        )
        assert max(jax.tree_util.tree_leaves(diff)) > 0, name
    assert all(np.isfinite(float(v)) for v in m.values())
    # with the KL weight and the Q loss zeroed out the encoder would get no gradient at all:
    # check that the encoder is untouched when Q ignores z (reward-only target, gamma = 0)
    assert int(new.steps) == 1


def test_update_traces_once():
    nets = Networks(SMALL, OBS, A)
    state = init_learner(jax.random.PRNGKey(0), nets)
    body = chex.assert_max_traces(make_update(nets, jit=False), n=1)
    upd = jax.jit(body)
    for i in range(3):
        state, _ = upd(
            state,
            _batch(jax.random.PRNGKey(i)),
            _context(jax.random.PRNGKey(10 + i)),
            jax.random.PRNGKey(20 + i),
        )
    chex.clear_trace_counter()


def test_sac_mode_uses_constant_latent():
    cfg = SMALL.replace(use_context=False)
    nets = Networks(cfg, OBS, A)
    params = nets.init(jax.random.PRNGKey(0))
    z, mean, var = nets.posterior_sample(
        params["encoder"], _context(jax.random.PRNGKey(1)), jax.random.PRNGKey(2)
    )
    assert not jnp.any(z) and float(jnp.sum(kl_to_standard_normal(mean, var))) == 0.0


@pytest.mark.parametrize(
    "field,value",
    [
        ("latent_dim", 0),
        ("hidden", ()),
        ("lr", -1.0),
        ("gamma", 1.5),
        ("kl_weight", -0.1),
        ("batch_size", 2.5),
        ("log_std_min", 5.0),
    ],
)
def test_invalid_pearl_config_names_field(field, value):
    with pytest.raises(ConfigError, match=field):
        PearlConfig(**{field: value})


@pytest.mark.parametrize("target", [100.0, -100.0])
def test_auto_entropy_moves_alpha_towards_the_target_and_starts_at_the_paper_update(target):
    """Extension `auto_entropy`: alpha starts at 1, so the first step's networks equal the
    paper's update; log alpha then takes Adam steps of about lr, up while the policy's entropy is
    below the target (log pi + target > 0) and down while above, as the NumPy sign says."""
    on = Networks(SMALL.replace(auto_entropy=True, target_entropy=target), OBS, A)
    off = Networks(SMALL, OBS, A)
    s_on, s_off = init_learner(jax.random.PRNGKey(0), on), init_learner(jax.random.PRNGKey(0), off)
    assert float(s_on.log_alpha) == 0.0 and s_off.log_alpha is None
    up_on, up_off = make_update(on), make_update(off)
    args = (_batch(jax.random.PRNGKey(1)), _context(jax.random.PRNGKey(2)), jax.random.PRNGKey(3))
    n_on, m_on = up_on(s_on, *args)
    n_off, m_off = up_off(s_off, *args)
    chex.assert_trees_all_close(n_on.params, n_off.params, rtol=1e-6, atol=1e-7)
    assert float(m_on["alpha"]) == 1.0 and "alpha" not in m_off
    sign = np.sign(float(m_on["log_pi"]) + target)
    np.testing.assert_allclose(float(n_on.log_alpha), sign * SMALL.lr, rtol=1e-3)
    state, alphas = n_on, []
    for i in range(5):
        state, m = up_on(state, _batch(jax.random.PRNGKey(10 + i)), *args[1:])
        alphas.append(float(m["alpha"]))
    assert np.all(sign * np.diff(alphas) > 0), alphas
    assert (
        target_entropy(on) == target
        and target_entropy(Networks(SMALL.replace(auto_entropy=True), OBS, A)) == -A
    )


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"auto_entropy": 1}, "auto_entropy"),
        ({"auto_entropy": True, "target_entropy": "high"}, "target_entropy"),
        ({"auto_entropy": True, "target_entropy": float("nan")}, "target_entropy"),
        ({"target_entropy": -2.0}, "target_entropy"),
    ],
)
def test_invalid_auto_entropy_settings_name_the_field(changes, field):
    with pytest.raises(ConfigError, match=f"PearlConfig.{field}"):
        SMALL.replace(**changes)


def test_layer_norm_adds_scale_and_bias_to_critics_only():
    cfg = PearlConfig(hidden=(8, 8), encoder_hidden=(4,), latent_dim=2, layer_norm=True)
    p = Networks(cfg, OBS, A).init(jax.random.PRNGKey(0))
    names = lambda tree: {  # noqa: E731
        "/".join(str(getattr(k, "key", k)) for k in path)
        for path, _ in jax.tree_util.tree_flatten_with_path(tree)[0]
    }
    assert any("LayerNorm" in n for n in names(p["q"]))
    assert any("LayerNorm" in n for n in names(p["v"]))
    assert not any("LayerNorm" in n for n in names(p["policy"]))
    off = Networks(dataclasses.replace(cfg, layer_norm=False), OBS, A).init(jax.random.PRNGKey(0))
    assert not any("LayerNorm" in n for n in names(off["q"]))
