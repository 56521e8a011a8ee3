"""PEARL's SAC losses (method §7; paper Sec. III-A, Algorithm 1 lines 21-23), built once per agent.

`make_losses(nets)` returns the losses with the config's constants (discount, reward scale, KL
weight, policy regularisers, entropy target) bound, as brax's `sac.losses.make_losses`; the
learner differentiates them. Shapes: MB tasks in the meta-batch, B RL transitions per task, C
context transitions per task, O obs dim, A action dim, L latent dim. z is one posterior sample
per task, broadcast over B.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from mpcpearl_jax.pearl.networks import Networks, kl_to_standard_normal, tanh_gaussian


class Losses(NamedTuple):
    """The losses of one agent (`make_losses`)."""

    # (q_enc_params {q, encoder}, target_v_params, batch [MB, B], context [MB, C, D], key)
    # -> (L_phi, aux): the critic loss L_psi plus the encoder's KL term
    critic_encoder: Callable
    # (policy_params, q_params, x [MB, B, O], z [MB, B, L], key, alpha=None, expert=None)
    # -> (L_theta, aux); x is the observation, or the shared crowd encoder's features [MB, B, F]
    # (`pearl.crowd_shared`); expert = (mark [MB, B], action [MB, B, A]) with `pearl.imitation`
    policy: Callable
    # (v_params, x [MB, B, O], z [MB, B, L], v_target [MB, B]) -> the SAC value loss
    value: Callable
    # (log_alpha, log_pi) -> the entropy weight's loss (extension `auto_entropy`)
    temperature: Callable


def target_entropy(nets: Networks) -> float:
    """The entropy the `auto_entropy` extension steers to: the configured value, or minus the
    action dimension (the usual SAC heuristic)."""
    t = nets.cfg.target_entropy
    return -float(nets.action_dim) if t is None else float(t)


def make_losses(nets: Networks) -> Losses:
    """The losses of the agent `nets`, with its config's constants bound."""
    cfg = nets.cfg
    entropy_target = target_entropy(nets)
    # the networks on what the actor and V losses read: the observation, or the shared crowd
    # encoder's features (`pearl.crowd_shared`, computed once per step by the learner)
    if nets.shared:
        pi_out, q_out, v_out = nets.policy_head, nets.q_heads, nets.value_head
    else:
        pi_out, q_out, v_out = nets.policy_out, nets.q_values, nets.value

    def critic_encoder(q_enc_params, target_v_params, batch, context, key):
        """L_phi = L_psi + beta KL(q(z|c) || N(0, I)) (paper Sec. III-A), L_psi the Q TD error
        against reward_scale * c + gamma V_bar(s', z). The encoder gets gradients from the Q
        loss and the KL only. With a shared crowd encoder (`pearl.crowd_shared`) each
        observation is encoded once: s by the critics' encoder (trained by this loss), s' by
        the target V's copy (an exponential average of it), forward only."""
        z, mean, var = nets.posterior_sample(q_enc_params["encoder"], context, key)  # [MB, L]
        zb = jnp.broadcast_to(z[:, None, :], batch.obs.shape[:2] + z.shape[-1:])  # [MB, B, L]
        if nets.shared:
            feats = nets.encode(q_enc_params["q"], batch.obs)
            q1, q2 = nets.q_heads(q_enc_params["q"], feats, batch.action, zb)
            next_feats = nets.encode(target_v_params, batch.next_obs)
            target_v = nets.value_head(target_v_params, next_feats, jax.lax.stop_gradient(zb))
        else:
            q1, q2 = nets.q_values(q_enc_params["q"], batch.obs, batch.action, zb)
            target_v = nets.value(target_v_params, batch.next_obs, jax.lax.stop_gradient(zb))
        return td_and_kl(q1, q2, td_target(batch, target_v), z, mean, var)

    def td_target(batch, next_v):
        """reward_scale * c + gamma V(s') (the paper); detached."""
        q_target = cfg.reward_scale * batch.reward + (1.0 - batch.done) * cfg.gamma * next_v
        return jax.lax.stop_gradient(q_target)

    def td_and_kl(q1, q2, q_target, z, mean, var):
        """(L_psi + beta KL, aux): the twin-Q squared TD errors and the encoder's KL term."""
        q_loss = jnp.mean((q1 - q_target) ** 2) + jnp.mean((q2 - q_target) ** 2)
        kl = jnp.sum(kl_to_standard_normal(mean, var))  # summed over tasks (method §7)
        loss = q_loss + cfg.kl_weight * kl
        return loss, {"q_loss": q_loss, "kl": kl, "z": z, "q1_mean": jnp.mean(q1)}

    def policy(policy_params, q_params, x, z, key, alpha=None, expert=None):
        """L_theta = KL(pi || exp(Q)/Z) = E[log pi - min_i Q_i] + the mean and log-std
        regularisers (paper Sec. III-A). z is detached (no policy gradient into the encoder).
        Extension `auto_entropy`: alpha (a detached scalar) weighs log pi in the loss and in
        the V target, E[alpha log pi - min_i Q_i]; None = 1 as in the paper. Extension
        `imitation` (`expert` given): + imitation x mean |min_i Q_i| (detached) x
        `behaviour_cloning`, so that the weight does not depend on the scale of the returns."""
        mean, log_std = pi_out(policy_params, x, z)
        action, log_pi = tanh_gaussian(mean, log_std).sample_and_log_prob(seed=key)
        q1, q2 = q_out(q_params, x, action, z)
        min_q = jnp.minimum(q1, q2)
        entropy_term = log_pi if alpha is None else alpha * log_pi
        loss = jnp.mean(entropy_term - min_q)
        loss += cfg.policy_mean_reg * jnp.mean(mean**2) + cfg.policy_std_reg * jnp.mean(log_std**2)
        aux = {"log_pi": jnp.mean(log_pi), "v_target": min_q - entropy_term}
        if expert is not None:
            bc, kept = behaviour_cloning(q_params, x, z, mean, min_q, *expert)
            # on the critic's scale, as TD3+BC (Fujimoto and Gu, 2021) weighs its two terms
            q_scale = jax.lax.stop_gradient(jnp.mean(jnp.abs(min_q)))
            loss += cfg.imitation * q_scale * bc
            aux.update(bc_loss=bc, bc_kept=kept)
        return loss, aux

    def behaviour_cloning(q_params, x, z, mean, min_q, mark, expert_action):
        """The MPC as a teacher (extension `imitation`; Nair et al., ICRA 2018, eq. (3)-(4)):
        sum over the batch's MPC transitions of ||tanh(mean(s)) - a_MPC||^2, each kept only
        where min_i Q_i(s, a_MPC) >= min_i Q_i(s, a~pi) (the Q-filter, critic detached), divided
        by the number of MPC transitions in the batch (1 if none). Returns (the term, the share
        of MPC transitions kept)."""
        q1, q2 = q_out(q_params, x, expert_action, z)
        better = jnp.minimum(q1, q2) >= min_q
        keep = jax.lax.stop_gradient(mark * better.astype(mark.dtype))
        err = jnp.sum((jnp.tanh(mean) - expert_action) ** 2, axis=-1)
        n = jnp.maximum(jnp.sum(mark), 1.0)
        return jnp.sum(keep * err) / n, jnp.sum(keep) / n

    def value(v_params, x, z, v_target):
        """SAC value loss (V_bar's source; method §7): (V(s, z) - [min_i Q_i(s, a~pi, z) -
        log pi(a|s, z)])^2, z detached. `v_target` comes from the policy loss's sample and
        min-Q (the authors' code reuses the same `min_q_new_actions` for both losses)."""
        v = v_out(v_params, x, z)
        return jnp.mean((v - jax.lax.stop_gradient(v_target)) ** 2)

    def temperature(log_alpha, log_pi):
        """Automatic entropy tuning (extension `auto_entropy`; Haarnoja et al. 2018b): -log_alpha
        (log pi + target entropy), log pi detached, so alpha grows while the policy's entropy is
        below the target and shrinks while it is above."""
        return -log_alpha * jax.lax.stop_gradient(jnp.mean(log_pi) + entropy_target)

    return Losses(critic_encoder, policy, value, temperature)
