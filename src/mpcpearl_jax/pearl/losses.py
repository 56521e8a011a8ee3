"""PEARL's SAC losses (method §7; paper Sec. III-A, Algorithm 1 lines 18-23).

Shapes: MB tasks in the meta-batch, B RL transitions per task, C context transitions per task,
O obs dim, A action dim, L latent dim. z is one posterior sample per task, broadcast over B.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mpcpearl_jax.pearl.networks import Networks, kl_to_standard_normal, tanh_gaussian


def critic_encoder_loss(
    q_enc_params,
    target_v_params,
    nets: Networks,
    batch,
    context,
    key,
    gamma: float,
    reward_scale: float,
    kl_weight: float,
):
    """L_psi (Q TD error, paper: critic loss) + L_phi = L_psi + beta KL(q(z|c) || N(0, I)).

    The encoder gets gradients from the Q loss and the KL only. Returns (loss, aux).
    """
    z, mean, var = nets.posterior_sample(q_enc_params["encoder"], context, key)  # [MB, L]
    zb = jnp.broadcast_to(z[:, None, :], batch.obs.shape[:2] + z.shape[-1:])  # [MB, B, L]
    q1, q2 = nets.q_values(q_enc_params["q"], batch.obs, batch.action, zb)
    target_v = nets.value(target_v_params, batch.next_obs, jax.lax.stop_gradient(zb))
    q_target = reward_scale * batch.reward + (1.0 - batch.done) * gamma * target_v
    q_target = jax.lax.stop_gradient(q_target)
    q_loss = jnp.mean((q1 - q_target) ** 2) + jnp.mean((q2 - q_target) ** 2)
    kl = jnp.sum(kl_to_standard_normal(mean, var))  # summed over tasks (method §7)
    loss = q_loss + kl_weight * kl
    return loss, {"q_loss": q_loss, "kl": kl, "z": z, "q1_mean": jnp.mean(q1)}


def value_loss(v_params, nets: Networks, obs, z, v_target):
    """SAC value loss: (V(s, z) - [min_i Q_i(s, a~pi, z) - log pi(a|s, z)])^2, z detached.

    `v_target` [MB, B] is precomputed from the policy loss's sample and min-Q (the authors' code
    reuses the same `min_q_new_actions` for both losses).
    """
    v = nets.value(v_params, obs, z)
    return jnp.mean((v - jax.lax.stop_gradient(v_target)) ** 2)


def policy_loss(
    policy_params,
    nets: Networks,
    q_params,
    obs,
    z,
    key,
    mean_reg,
    std_reg,
    alpha=None,
):
    """Paper's actor loss L_theta = KL(pi || exp(Q)/Z) = E[log pi - min_i Q_i] + regularisers.

    z is detached (no policy gradient into the encoder). Extension
    `PearlConfig.auto_entropy`: alpha (a detached scalar) weighs log pi in the loss and in the V
    target, E[alpha log pi - min_i Q_i]; None = 1 as in the paper. Returns (loss, aux).
    """
    mean, log_std = nets.policy_out(policy_params, obs, z)
    action, log_pi = tanh_gaussian(mean, log_std).sample_and_log_prob(seed=key)
    q1, q2 = nets.q_values(q_params, obs, action, z)
    min_q = jnp.minimum(q1, q2)
    entropy_term = log_pi if alpha is None else alpha * log_pi
    loss = jnp.mean(entropy_term - min_q)
    loss += mean_reg * jnp.mean(mean**2) + std_reg * jnp.mean(log_std**2)
    return loss, {"log_pi": jnp.mean(log_pi), "v_target": min_q - entropy_term}


def temperature_loss(log_alpha, log_pi, target_entropy: float):
    """Automatic entropy tuning (extension `PearlConfig.auto_entropy`): -log_alpha (log pi +
    target entropy), log pi detached, so alpha grows while the policy's entropy is below the
    target and shrinks while it is above."""
    return -log_alpha * jax.lax.stop_gradient(jnp.mean(log_pi) + target_entropy)
