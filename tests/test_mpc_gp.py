"""GP prediction of people (paper appendix) against a small NumPy GP."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.mpc import MPCConfig, gp

CFG = MPCConfig(gp_mode="fixed", gp_lengthscale=0.7, gp_signal_std=0.3, gp_noise_std=0.05)


def numpy_gp(x, y, query, ell, sf, sn):
    """Textbook GP regression (Rasmussen & Williams eq. 2.25-2.26), one output axis."""

    def k(a, b):
        d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
        return sf**2 * np.exp(-0.5 * d2 / ell**2)

    gram = k(x, x) + sn**2 * np.eye(len(x))
    ks = k(query[None, :], x)[0]
    mean = ks @ np.linalg.solve(gram, y)
    var = sf**2 - ks @ np.linalg.solve(gram, ks)
    nll = 0.5 * y @ np.linalg.solve(gram, y) + 0.5 * np.linalg.slogdet(gram)[1]
    return mean, var, nll + 0.5 * len(x) * np.log(2 * np.pi)


def curved_history(n=11):
    s = np.linspace(0, 1.5, n)
    return np.column_stack([s - 1.0, 0.3 * np.sin(2 * s)]).astype(np.float32)


def test_posterior_and_likelihood_match_numpy():
    hist = curved_history()
    x, y = hist[:-1], hist[1:] - hist[:-1]
    hyper = gp.initial_hyper(CFG)
    query = np.array([0.7, 0.2], np.float32)
    mean, var = gp.posterior(jnp.asarray(x), jnp.asarray(y), hyper, jnp.asarray(query))
    for j in range(2):
        m_ref, v_ref, nll_ref = numpy_gp(
            x.astype(float), y[:, j].astype(float), query, 0.7, 0.3, 0.05
        )
        assert float(mean[j]) == pytest.approx(m_ref, abs=1e-4)
        assert float(var[j]) == pytest.approx(v_ref, abs=1e-4)
        nll = gp.neg_log_marginal_likelihood(
            hyper.log_params[j], jnp.asarray(x), jnp.asarray(y[:, j])
        )
        assert float(nll) == pytest.approx(nll_ref, rel=1e-3, abs=1e-3)


def test_propagation_matches_numpy_recursion():
    hist = curved_history()
    x, y = hist[:-1].astype(float), (hist[1:] - hist[:-1]).astype(float)
    mu, var = hist[-1].astype(float), np.zeros(2)
    ref_mu, ref_var = [], []
    for _ in range(CFG.horizon):  # mu_{k+1} = mu_k + m(mu_k), S_{k+1} = S_k + s^2(mu_k)
        out = [numpy_gp(x, y[:, j], mu, 0.7, 0.3, 0.05) for j in range(2)]
        mu = mu + np.array([o[0] for o in out])
        var = var + np.array([o[1] for o in out])
        ref_mu.append(mu)
        ref_var.append(var)
    got_mu, got_var = gp.predict(jnp.asarray(hist), CFG.horizon, gp.initial_hyper(CFG), 1e-4)
    np.testing.assert_allclose(got_mu, np.array(ref_mu), atol=1e-4)
    np.testing.assert_allclose(got_var, np.array(ref_var), atol=1e-4)
    assert np.all(np.diff(np.asarray(got_var), axis=0) >= 0)


def test_fit_increases_marginal_likelihood():
    hist = curved_history()
    x, y = jnp.asarray(hist[:-1]), jnp.asarray(hist[1:] - hist[:-1])
    init = gp.initial_hyper(CFG)
    fitted = gp.fit_hyper(x, y, init, steps=30, lr=0.1)
    nll = jax.vmap(gp.neg_log_marginal_likelihood, in_axes=(0, None, 1))
    assert np.all(np.asarray(nll(fitted.log_params, x, y)) < np.asarray(nll(init.log_params, x, y)))


def test_static_person_has_zero_variance_and_history_is_clamped():
    human_pos = jnp.zeros((81, 1, 2)).at[:, 0].set(jnp.array([1.0, 2.0]))
    human_pos = human_pos.at[5:, 0, 0].add(jnp.arange(76) * 0.1)  # starts walking at step 5
    hist = gp.history(human_pos[:, 0], jnp.int32(3), 10)
    assert hist.shape == (11, 2)
    np.testing.assert_allclose(hist, np.tile([1.0, 2.0], (11, 1)))  # before t = 0: first position
    mean, var = gp.predict_person(hist, MPCConfig())
    np.testing.assert_allclose(mean, np.tile([1.0, 2.0], (10, 1)))
    np.testing.assert_allclose(var, 0.0)
    mean, var = gp.predict_person(gp.history(human_pos[:, 0], jnp.int32(40), 10), MPCConfig())
    assert float(mean[-1, 0] - human_pos[40, 0, 0]) > 0.5  # keeps walking in +x
    assert np.all(np.isfinite(np.asarray(var)))


def test_masked_people_are_never_nearest():
    humans = jnp.array([[0.1, 0.0], [5.0, 5.0], [0.2, 0.0], [3.0, 0.0]])
    mask = jnp.array([False, True, False, True])
    idx, valid = gp.nearest_people(jnp.zeros(2), humans, mask, 2)
    assert sorted(np.asarray(idx).tolist()) == [1, 3] and bool(valid.all())
    idx, valid = gp.nearest_people(jnp.zeros(2), humans, jnp.array([False, False, False, True]), 2)
    assert int(idx[0]) == 3 and np.asarray(valid).tolist() == [True, False]


def test_predict_row_shapes_and_sample_moments():
    t_len = 81
    walk = jnp.stack([jnp.linspace(-3, 3, t_len), jnp.zeros(t_len)], axis=-1)
    human_pos = jnp.stack([walk, walk + 1.0, walk - 7.0], axis=1)
    mask = jnp.ones((t_len, 3), bool)
    cfg = MPCConfig(num_samples=4000)
    samples, valid = jax.jit(
        lambda k: gp.predict_row(k, jnp.array([0.0, 0.5, 0.0]), jnp.int32(40), human_pos, mask, cfg)
    )(jax.random.PRNGKey(0))
    assert samples.shape == (10, 2, 4000, 2) and bool(valid.all())
    hist = gp.history(human_pos[:, 0], jnp.int32(40), 10)
    mean, var = gp.predict_person(hist, cfg)
    np.testing.assert_allclose(
        samples[:, 0].mean(1), mean, atol=5 * float(jnp.sqrt(var.max() / 4000)) + 1e-3
    )
