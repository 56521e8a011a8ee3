"""The host MPC's NumPy model and QP linearization against the JAX model and finite differences."""

import jax.numpy as jnp
import numpy as np

from mpcpearl_jax.envs import make_env
from mpcpearl_jax.envs.dynamics import bicycle_step as jax_step
from mpcpearl_jax.mpc import MPCConfig, RowProblem, model, solver_params
from mpcpearl_jax.mpc.problem import linearize_problem

RNG = np.random.default_rng(0)


def random_pose_input(n):
    pose = np.column_stack([RNG.uniform(-4, 4, n), RNG.uniform(-4, 4, n), RNG.uniform(-3, 3, n)])
    u = np.column_stack([RNG.uniform(0, 5, n), RNG.uniform(-1.4, 1.4, n)])
    return pose, u


def test_numpy_step_equals_jax_step():
    pose, u = random_pose_input(200)
    u[:5, 1] = np.array([-np.pi / 2, np.pi / 2, 0.0, 1e-6, -1e-6])  # box edges and straight
    for dt in (0.05, 0.04):
        ref = np.asarray(jax_step(jnp.asarray(pose), jnp.asarray(u), dt), np.float64)
        got = model.bicycle_step(pose, u, dt)
        np.testing.assert_allclose(got, ref, atol=1e-5)


def test_jacobians_match_finite_differences():
    pose, u = random_pose_input(50)
    a, b = model.linearize(pose, u, 0.05)
    h = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fd = (
            model.bicycle_step(pose + e, u, 0.05, wrap=False)
            - model.bicycle_step(pose - e, u, 0.05, wrap=False)
        ) / (2 * h)
        np.testing.assert_allclose(a[:, :, j], fd, atol=1e-6)
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (
            model.bicycle_step(pose, u + e, 0.05, wrap=False)
            - model.bicycle_step(pose, u - e, 0.05, wrap=False)
        ) / (2 * h)
        np.testing.assert_allclose(b[:, :, j], fd, atol=1e-5)


def test_distance_gradients_match_finite_differences():
    p = RNG.uniform(-3, 3, (100, 2))
    lo = np.array([-0.5, 0.2])
    hi = np.array([0.7, 1.1])
    q = RNG.uniform(-3, 3, (100, 2))
    h = 1e-6
    for dist_fn in (lambda x: model.box_distance(x, lo, hi), lambda x: model.point_distance(x, q)):
        d, g = dist_fn(p)
        outside = d > 1e-3
        for j in range(2):
            e = np.zeros(2)
            e[j] = h
            fd = (dist_fn(p + e)[0] - dist_fn(p - e)[0]) / (2 * h)
            np.testing.assert_allclose(g[outside, j], fd[outside], atol=1e-5)


def _row_problem(num_people=2):
    samples = np.array([0.6, -0.4]) + 0.2 * RNG.standard_normal((10, num_people, 100, 2))
    return RowProblem(
        x0=np.array([-1.0, 0.0, 0.1]),
        goal=np.array([3.0, 0.0]),
        samples=samples,
        valid=np.ones(num_people, bool),
        static_lo=np.array([[0.5, 1.0], [2.0, -3.0]]),
        static_hi=np.array([[0.5, 1.0], [4.0, -2.0]]),
        static_radius=np.array([0.5, 0.0]),
    )


def test_qp_linearization_is_a_first_order_model_of_the_nonlinear_problem():
    env = make_env("restaurant")
    p = solver_params(MPCConfig(), env.config, num_static=2)
    prob = _row_problem()
    u = np.column_stack([np.full(10, 3.0), np.linspace(-0.3, 0.3, 10)])
    xs = model.rollout(prob.x0, u, p.dt)
    lin = linearize_problem(p, prob, u, xs)
    # dynamics rows (eq. (3b)) hold exactly at the linearization point ...
    resid = xs[1:] - np.einsum("kij,kj->ki", lin.b, u)
    resid[1:] -= np.einsum("kij,kj->ki", lin.a[1:], xs[1:-1])
    np.testing.assert_allclose(resid, lin.dyn_rhs, atol=1e-12)
    # ... and the linear rollout is a first-order model of the nonlinear one
    du = RNG.standard_normal(u.shape) * np.array([1.0, 0.2])
    for eps, tol in ((1e-2, 2e-3), (1e-3, 2e-5)):
        x_nl = model.rollout(prob.x0, u + eps * du, p.dt)
        x_lin = np.empty_like(x_nl)
        x_lin[0] = prob.x0
        for k in range(10):
            dx = x_lin[k] - xs[k]
            x_lin[k + 1] = xs[k + 1] + lin.a[k] @ dx + lin.b[k] @ (eps * du[k])
        assert np.max(np.abs(x_nl - x_lin)) < tol
    # static half-planes (eq. (4c)): bd(p) ~ bd(pbar) + g.(p - pbar), conservative (convex bd)
    pos = xs[1:, :2]
    shift = 0.05 * RNG.standard_normal(pos.shape)
    bd_new, _ = model.box_distance((pos + shift)[:, None, :], prob.static_lo, prob.static_hi)
    need = p.static_margin + prob.static_radius
    lin_bd = need - lin.stat_lo + np.einsum("ksj,kj->ks", lin.stat_grad, pos + shift)
    assert np.all(bd_new >= lin_bd - 1e-9)
    assert np.max(np.abs(bd_new - lin_bd)) < 0.01
    # sample rows (eq. (4b)): linearized loss upper-bounds the exact loss of each kept sample
    lin_loss = lin.samp_lo - np.einsum("ktj,kj->kt", lin.samp_grad, pos + shift)
    d_all = np.linalg.norm((pos + shift)[:, None, None, :] - prob.samples, axis=-1)
    exact_max = (p.eps_dynamic - d_all).max(axis=(1, 2))
    assert np.all(lin_loss.max(axis=1) >= exact_max - 0.05)  # the top samples are kept
    assert np.all(lin_loss <= p.eps_dynamic - d_all.min(axis=1)[:, :1].min() + 1.0)


def test_saa_cvar_equals_brute_force_minimum():
    for alpha in (0.95, 0.9, 0.97):
        losses = RNG.standard_normal((7, 100))
        xis = np.linspace(-4, 4, 40001)
        brute = np.array(
            [
                np.min(xis + np.maximum(row[None, :] - xis[:, None], 0).mean(1) / (1 - alpha))
                for row in losses
            ]
        )
        np.testing.assert_allclose(model.saa_cvar(losses, alpha), brute, atol=1e-3)
