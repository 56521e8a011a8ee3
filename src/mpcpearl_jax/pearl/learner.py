"""The PEARL update (Algorithm 1, training stage) and its state.

`make_update(nets)` builds one gradient step over a meta-batch; the trainer composes it into a
`lax.scan` over steps that samples meta-batches from device buffers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax import Array

from mpcpearl_jax.pearl import losses
from mpcpearl_jax.pearl.config import PearlConfig
from mpcpearl_jax.pearl.networks import Networks
from mpcpearl_jax.pearl.types import Transitions, context_from

__all__ = [
    "LearnerState",
    "acting_params",
    "Transitions",
    "context_from",
    "init_learner",
    "make_update",
]


@struct.dataclass
class LearnerState:
    """All trainable state of one agent."""

    params: dict  # {policy, q, v, encoder}
    target_v: dict
    opt_state: dict  # {q_enc, policy, v}
    steps: Array  # int32 gradient steps taken
    # log of the learned entropy weight (extension `PearlConfig.auto_entropy`); None when off
    log_alpha: Array | None = None


def acting_params(params: dict) -> dict:
    """The {policy, encoder} part of the parameters: what acting and adaptation need."""
    return {"policy": params["policy"], "encoder": params["encoder"]}


def _optimizer(cfg: PearlConfig) -> optax.GradientTransformation:
    adam = optax.adam(cfg.lr)
    if cfg.max_grad_norm is None:
        return adam
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), adam)


def init_learner(key: Array, nets: Networks) -> LearnerState:
    """Fresh parameters, optimizer states and target V of the agent `nets`."""
    params = nets.init(key)
    opt = _optimizer(nets.cfg)
    opt_state = {
        "q_enc": opt.init({"q": params["q"], "encoder": params["encoder"]}),
        "policy": opt.init(params["policy"]),
        "v": opt.init(params["v"]),
    }
    log_alpha = None
    if nets.cfg.auto_entropy:  # alpha starts at 1, the paper's temperature
        log_alpha = jnp.zeros((), jnp.float32)
        opt_state["alpha"] = opt.init(log_alpha)
    return LearnerState(params, params["v"], opt_state, jnp.zeros((), jnp.int32), log_alpha)


def make_update(nets: Networks, jit: bool = True):
    """`update(state, batch [MB, B], context [MB, C, D], key) -> (state, metrics)`: one PEARL
    gradient step of the agent `nets` (Algorithm 1 lines 20-23, the meta-batch sampled by the
    caller); jit=False gives the plain function, for composing into scans (see `trainer`). The
    losses are built once (`losses.make_losses`)."""
    opt, loss = _optimizer(nets.cfg), losses.make_losses(nets)

    def opt_step(params, grads, opt_state):
        upd, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, upd), opt_state

    def update(
        state: LearnerState, batch: Transitions, context: Array, key: Array
    ) -> tuple[LearnerState, dict]:
        # order as in the authors' code: Q + encoder, then the policy against the updated Q,
        # then V and alpha from the same policy sample
        k_z, k_pi = jax.random.split(key)
        p, opt_in = state.params, state.opt_state
        alpha = None if state.log_alpha is None else jnp.exp(state.log_alpha)
        # 1. Q and encoder: L_phi = L_psi + beta KL (line 22)
        q_enc = {"q": p["q"], "encoder": p["encoder"]}
        (qe_loss, aux), grads = jax.value_and_grad(loss.critic_encoder, has_aux=True)(
            q_enc, state.target_v, batch, context, k_z
        )
        q_enc, os_qe = opt_step(q_enc, grads, opt_in["q_enc"])
        z = jax.lax.stop_gradient(aux["z"])
        zb = jnp.broadcast_to(z[:, None, :], batch.obs.shape[:2] + z.shape[-1:])
        # what the actor and V read: the observation, or (`pearl.crowd_shared`) the updated
        # critics' crowd features, computed once and detached
        x = batch.obs
        if nets.shared:
            x = jax.lax.stop_gradient(nets.encode(q_enc["q"], batch.obs))
        # extension `imitation`: the MPC's actions in the batch, marked by the collection
        expert = None
        if nets.cfg.imitation > 0:
            if batch.expert is None:
                raise ValueError("pearl.imitation needs the batch's expert marks")
            expert = (batch.expert, batch.action)
        # 2. policy L_theta (line 22), z detached, with the updated Q
        (pi_loss, pi_aux), g_pi = jax.value_and_grad(loss.policy, has_aux=True)(
            p["policy"], q_enc["q"], x, zb, k_pi, alpha, expert
        )
        policy, os_pi = opt_step(p["policy"], g_pi, opt_in["policy"])
        # 3. value (line 23), target from the same policy sample and the updated Q
        v_target = jax.lax.stop_gradient(pi_aux["v_target"])
        v_loss, g_v = jax.value_and_grad(loss.value)(p["v"], x, zb, v_target)
        v, os_v = opt_step(p["v"], g_v, opt_in["v"])
        opt_state = {"q_enc": os_qe, "policy": os_pi, "v": os_v}
        # 4. entropy weight (extension `auto_entropy`), from the same policy sample's log pi
        log_alpha = state.log_alpha
        if log_alpha is not None:
            g_a = jax.grad(loss.temperature)(log_alpha, pi_aux["log_pi"])
            log_alpha, opt_state["alpha"] = opt_step(log_alpha, g_a, opt_in["alpha"])
        params = {"policy": policy, "q": q_enc["q"], "v": v, "encoder": q_enc["encoder"]}
        if nets.shared:  # the policy and V act with the critics' updated encoder
            params = nets.share_crowd(params)
        # the target V (with a shared encoder, its copy too: the target encoder)
        target_v = optax.incremental_update(params["v"], state.target_v, nets.cfg.tau)
        new = LearnerState(params, target_v, opt_state, state.steps + 1, log_alpha)
        metrics = {
            "q_loss": aux["q_loss"],
            "kl": aux["kl"],
            "policy_loss": pi_loss,
            "v_loss": v_loss,
            "log_pi": pi_aux["log_pi"],
            "q_mean": aux["q1_mean"],
            "loss_total": qe_loss,
        }
        if alpha is not None:
            metrics["alpha"] = alpha
        if expert is not None:
            metrics["bc_loss"], metrics["bc_kept"] = pi_aux["bc_loss"], pi_aux["bc_kept"]
        return new, metrics

    return jax.jit(update) if jit else update
