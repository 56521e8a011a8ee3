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
    "target_entropy",
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


def target_entropy(nets: Networks) -> float:
    """The entropy the `auto_entropy` extension steers to: the configured value, or minus the
    action dimension (the usual SAC heuristic)."""
    t = nets.cfg.target_entropy
    return -float(nets.action_dim) if t is None else float(t)


def _update(
    nets: Networks,
    cfg: PearlConfig,
    opt,
    state: LearnerState,
    batch: Transitions,
    context: Array,
    key: Array,
) -> tuple[LearnerState, dict]:
    """One PEARL gradient step (order as in the authors' code: Q+encoder, then V, policy)."""
    k_z, k_pi = jax.random.split(key)
    p = state.params
    alpha = None if state.log_alpha is None else jnp.exp(state.log_alpha)
    # 1. Q and encoder: L_psi + beta KL (paper L_phi).
    q_enc = {"q": p["q"], "encoder": p["encoder"]}
    (qe_loss, aux), grads = jax.value_and_grad(losses.critic_encoder_loss, has_aux=True)(
        q_enc, state.target_v, nets, batch, context, k_z, cfg.gamma, cfg.reward_scale, cfg.kl_weight
    )
    upd, os_qe = opt.update(grads, state.opt_state["q_enc"], q_enc)
    q_enc = optax.apply_updates(q_enc, upd)
    z = jax.lax.stop_gradient(aux["z"])
    zb = jnp.broadcast_to(z[:, None, :], batch.obs.shape[:2] + z.shape[-1:])
    # 2. policy (z detached), with the updated Q.
    (pi_loss, pi_aux), g_pi = jax.value_and_grad(losses.policy_loss, has_aux=True)(
        p["policy"],
        nets,
        q_enc["q"],
        batch.obs,
        zb,
        k_pi,
        cfg.policy_mean_reg,
        cfg.policy_std_reg,
        alpha,
    )
    upd, os_pi = opt.update(g_pi, state.opt_state["policy"], p["policy"])
    policy = optax.apply_updates(p["policy"], upd)
    # 3. value (z detached), target from the same policy sample and updated Q.
    v_loss, g_v = jax.value_and_grad(losses.value_loss)(
        p["v"], nets, batch.obs, zb, jax.lax.stop_gradient(pi_aux["v_target"])
    )
    upd, os_v = opt.update(g_v, state.opt_state["v"], p["v"])
    v = optax.apply_updates(p["v"], upd)
    target_v = optax.incremental_update(v, state.target_v, cfg.tau)

    opt_state = {"q_enc": os_qe, "policy": os_pi, "v": os_v}
    # 4. entropy weight (extension `auto_entropy`), from the same policy sample's log pi
    log_alpha = state.log_alpha
    if log_alpha is not None:
        g_a = jax.grad(losses.temperature_loss)(log_alpha, pi_aux["log_pi"], target_entropy(nets))
        upd, opt_state["alpha"] = opt.update(g_a, state.opt_state["alpha"], log_alpha)
        log_alpha = optax.apply_updates(log_alpha, upd)

    params = {"policy": policy, "q": q_enc["q"], "v": v, "encoder": q_enc["encoder"]}
    new_state = LearnerState(
        params,
        target_v,
        opt_state,
        state.steps + 1,
        log_alpha,
    )
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
    return new_state, metrics


def make_update(nets: Networks, jit: bool = True):
    """`update(state, batch [MB, B], context [MB, C, D], key) -> (state, metrics)`: one
    gradient step of the agent `nets`; jit=False gives the plain function, for composing into
    scans (see `trainer`)."""
    cfg, opt = nets.cfg, _optimizer(nets.cfg)

    def update(
        state: LearnerState,
        batch: Transitions,
        context: Array,
        key: Array,
    ):
        return _update(nets, cfg, opt, state, batch, context, key)

    return jax.jit(update) if jit else update
