"""GP prediction of people (paper Sec. III-B and appendix "Details of GPR"), pure JAX.

Per person and axis an RBF-kernel GP maps the 2-D position to the per-step displacement, trained
on the last N_GP transitions. The K-step prediction propagates the mean through the GP mean and
adds the GP variance at the mean (inputs and outputs assumed uncorrelated):

    mu_{k+1} = mu_k + m(mu_k),   S_{k+1} = S_k + s^2(mu_k),   mu_0 = x_t, S_0 = 0.

Everything acts on one person (vmap over people and envs). Hyperparameters are either fixed or
fitted by maximum marginal likelihood with a fixed number of Adam steps.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from mpcpearl_jax.mpc.config import MPCConfig

_JITTER = 1e-6
# box on the log-hyperparameters (lengthscale, signal std, noise std), for a stable Cholesky
# (NumPy float32, bit-identical to jnp.log: importing the package must not start a JAX backend,
# so that jax.distributed.initialize can still run after it)
_LOG_LO = np.log(np.array([0.05, 1e-3, 1e-3], np.float32))
_LOG_HI = np.log(np.array([20.0, 2.0, 0.5], np.float32))


class GPHyper(NamedTuple):
    """Log hyperparameters per output axis: [2, 3] = (log lengthscale, log sf, log sn)."""

    log_params: Array


def initial_hyper(cfg: MPCConfig) -> GPHyper:
    """The configured values for both axes ([2, 3])."""
    row = jnp.log(jnp.array([cfg.gp_lengthscale, cfg.gp_signal_std, cfg.gp_noise_std]))
    return GPHyper(jnp.tile(row, (2, 1)))


def history(human_pos: Array, t: Array, n_gp: int) -> Array:
    """Positions at steps t - N_GP .. t, indices clamped to [0, T]: [..., N_GP + 1, 2].

    human_pos: [T + 1, ..., 2] (any trailing person axes). Before the episode people stood at their
    first position.
    """
    idx = jnp.clip(t - n_gp + jnp.arange(n_gp + 1), 0, human_pos.shape[0] - 1)
    return jnp.moveaxis(human_pos[idx], 0, -2)


def rbf(x1: Array, x2: Array, log_ell: Array, log_sf: Array) -> Array:
    """RBF kernel sf^2 exp(-|x1 - x2|^2 / (2 ell^2)); x1 [N, 2], x2 [P, 2] -> [N, P]."""
    d2 = jnp.sum((x1[:, None, :] - x2[None, :, :]) ** 2, axis=-1)
    return jnp.exp(2.0 * log_sf) * jnp.exp(-0.5 * d2 / jnp.exp(2.0 * log_ell))


def _gram_cholesky(x: Array, theta: Array) -> Array:
    """Cholesky factor of K(x, x) + (sn^2 + jitter) I for one axis; theta [3]."""
    gram = rbf(x, x, theta[0], theta[1])
    return jnp.linalg.cholesky(gram + (jnp.exp(2.0 * theta[2]) + _JITTER) * jnp.eye(x.shape[0]))


def neg_log_marginal_likelihood(theta: Array, x: Array, y: Array) -> Array:
    """-log p(y | x, theta) of one axis; x [N, 2], y [N], theta [3]."""
    chol = _gram_cholesky(x, theta)
    a = jax.scipy.linalg.cho_solve((chol, True), y)
    return 0.5 * y @ a + jnp.sum(jnp.log(jnp.diag(chol))) + 0.5 * y.shape[0] * jnp.log(2 * jnp.pi)


def fit_hyper(x: Array, y: Array, init: GPHyper, steps: int, lr: float) -> GPHyper:
    """Maximum marginal likelihood by `steps` Adam steps on the log-parameters, per axis.

    x [N, 2] inputs, y [N, 2] displacements -> GPHyper [2, 3]. Falls back to `init` if the fit
    produced non-finite values.
    """
    grad = jax.vmap(jax.grad(neg_log_marginal_likelihood), in_axes=(0, None, 1))

    def adam(carry, i):
        th, m, v = carry
        g = grad(th, x, y)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        m = 0.9 * m + 0.1 * g
        v = 0.999 * v + 0.001 * g * g
        step = lr * (m / (1 - 0.9 ** (i + 1))) / (jnp.sqrt(v / (1 - 0.999 ** (i + 1))) + 1e-8)
        return (jnp.clip(th - step, _LOG_LO, _LOG_HI), m, v), None

    th0 = init.log_params
    (th, _, _), _ = jax.lax.scan(
        adam, (th0, jnp.zeros_like(th0), jnp.zeros_like(th0)), jnp.arange(steps)
    )
    return GPHyper(jnp.where(jnp.all(jnp.isfinite(th)), th, th0))


def posterior(x: Array, y: Array, hyper: GPHyper, query: Array) -> tuple[Array, Array]:
    """GP mean and latent variance of the displacement at one query [2] -> ([2], [2])."""

    def one_axis(theta, y_j):
        chol = _gram_cholesky(x, theta)
        k_star = rbf(query[None, :], x, theta[0], theta[1])[0]  # [N]
        mean = k_star @ jax.scipy.linalg.cho_solve((chol, True), y_j)
        w = jax.scipy.linalg.solve_triangular(chol, k_star, lower=True)
        var = jnp.exp(2.0 * theta[1]) - w @ w
        return mean, jnp.maximum(var, 0.0)

    return jax.vmap(one_axis, in_axes=(0, 1))(hyper.log_params, y)


def predict(hist: Array, horizon: int, hyper: GPHyper, static_tol: float) -> tuple[Array, Array]:
    """K-step prediction of one person from its history [N_GP + 1, 2].

    Returns mean and variance per axis at stages 1..K: ([K, 2], [K, 2]). A person who moved less
    than `static_tol` in the last step is static with zero variance (method §6).
    """
    x, y = hist[:-1], hist[1:] - hist[:-1]
    moving = jnp.linalg.norm(y[-1]) > static_tol

    def step(carry, _):
        mu, var = carry
        dm, dv = posterior(x, y, hyper, mu)
        nxt = (mu + dm, var + dv)
        return nxt, nxt

    _, (mus, vars_) = jax.lax.scan(step, (hist[-1], jnp.zeros(2)), None, length=horizon)
    still = jnp.broadcast_to(hist[-1], mus.shape)
    return jnp.where(moving, mus, still), jnp.where(moving, vars_, 0.0)


def predict_person(hist: Array, cfg: MPCConfig) -> tuple[Array, Array]:
    """Fit (or fix) the hyperparameters, then predict: hist [N_GP + 1, 2] -> ([K, 2], [K, 2])."""
    hyper = initial_hyper(cfg)
    if cfg.gp_mode == "fit":
        hyper = fit_hyper(hist[:-1], hist[1:] - hist[:-1], hyper, cfg.gp_fit_steps, cfg.gp_fit_lr)
    return predict(hist, cfg.horizon, hyper, cfg.gp_static_tol)


def nearest_people(pos: Array, humans: Array, mask: Array, n: int) -> tuple[Array, Array]:
    """Indices [n] of the n nearest present people to pos [2] (humans [H, 2], mask [H]) and a
    validity flag [n]; absent people are never selected (valid False when fewer than n present)."""
    d = jnp.where(mask, jnp.linalg.norm(humans - pos, axis=-1), jnp.inf)
    if humans.shape[0] < n:  # pad with invalid slots
        d = jnp.concatenate([d, jnp.full(n - humans.shape[0], jnp.inf)])
    idx = jnp.argsort(d)[:n]
    return jnp.minimum(idx, humans.shape[0] - 1), jnp.isfinite(d[idx])


def sample_predictions(key: Array, mean: Array, var: Array, num_samples: int) -> Array:
    """Samples from N(mean, diag var): mean, var [K, ..., 2] -> [K, ..., M, 2]."""
    eps = jax.random.normal(key, mean.shape[:-1] + (num_samples, 2), mean.dtype)
    return mean[..., None, :] + jnp.sqrt(var)[..., None, :] * eps


def predict_row(
    key: Array, pose: Array, t: Array, human_pos: Array, human_mask: Array, cfg: MPCConfig
) -> tuple[Array, Array]:
    """GP samples of the N_adapt nearest present people for one env.

    pose [3], t [], human_pos [T + 1, H, 2], human_mask [T + 1, H] ->
    samples [K, N_adapt, M, 2] at stages t+1..t+K, valid [N_adapt] bool.
    """
    tc = jnp.clip(t, 0, human_pos.shape[0] - 1)
    idx, valid = nearest_people(pose[:2], human_pos[tc], human_mask[tc], cfg.n_adapt)
    hist = history(human_pos[:, idx], t, cfg.n_gp)  # [N_adapt, N_GP + 1, 2]
    mean, var = jax.vmap(lambda h: predict_person(h, cfg))(hist)  # [N_adapt, K, 2]
    mean, var = jnp.swapaxes(mean, 0, 1), jnp.swapaxes(var, 0, 1)
    return sample_predictions(key, mean, var, cfg.num_samples), valid
