"""PEARL hyperparameters (method §7) as a frozen, validated dataclass."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from mpcpearl_jax.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class PearlConfig:
    """Networks, losses and update schedule of PEARL's SAC variant.

    Defaults are the authors' settings (method §7 / paper Table I).
    """

    latent_dim: int = 10
    hidden: tuple[int, ...] = (300, 300, 300)  # policy, Q, V
    encoder_hidden: tuple[int, ...] = (200, 200, 200)
    lr: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005  # target V soft update
    reward_scale: float = 100.0  # temperature 1 / reward_scale
    kl_weight: float = 0.1  # beta
    policy_mean_reg: float = 1e-3
    policy_std_reg: float = 1e-3
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    min_posterior_var: float = 1e-7
    meta_batch: int = 16  # tasks per gradient step
    batch_size: int = 256  # RL transitions per task
    context_size: int = 64  # context transitions per task
    max_grad_norm: float | None = None  # None = no clipping (authors)
    use_context: bool = True  # False: z = 0 always, no encoder (the paper's MPC-SAC baseline)
    # ---- extensions beyond the paper (off by default and in the `paper` preset)
    # Q-filtered behaviour cloning on MPC transitions (Nair et al. 2018): the policy loss adds
    # bc_weight * mean over MPC samples of 1[Q(s, a_mpc) > Q(s, pi(s))] |tanh(mu(s)) - a_mpc|^2.
    bc_weight: float = 0.0
    bc_q_filter: bool = True  # False: clone every MPC sample (no Q filter)
    layer_norm: bool = False  # LayerNorm after every hidden layer of the Q and V networks

    def __post_init__(self) -> None:
        n = type(self).__name__
        ints = ("latent_dim", "meta_batch", "batch_size", "context_size")
        for f in ints:
            v = getattr(self, f)
            if not (isinstance(v, int) and v > 0):
                raise ConfigError(f"{n}.{f}: must be a positive int, got {v!r}")
        for f in ("hidden", "encoder_hidden"):
            v = getattr(self, f)
            if not (len(v) > 0 and all(isinstance(h, int) and h > 0 for h in v)):
                raise ConfigError(f"{n}.{f}: must be a non-empty tuple of positive ints, got {v!r}")
        for f in ("lr", "reward_scale", "min_posterior_var"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{n}.{f}: must be a positive number, got {v!r}")
        for f in ("gamma", "tau"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and 0 <= v <= 1):
                raise ConfigError(f"{n}.{f}: must lie in [0, 1], got {v!r}")
        for f in ("kl_weight", "policy_mean_reg", "policy_std_reg", "bc_weight"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"{n}.{f}: must be a non-negative number, got {v!r}")
        for f in ("use_context", "layer_norm", "bc_q_filter"):
            if not isinstance(getattr(self, f), bool):
                raise ConfigError(f"{n}.{f}: must be true or false, got {getattr(self, f)!r}")
        if not self.log_std_min < self.log_std_max:
            raise ConfigError(f"{n}.log_std_min: must be below log_std_max")
        if self.max_grad_norm is not None and not self.max_grad_norm > 0:
            raise ConfigError(f"{n}.max_grad_norm: must be positive or None")

    def replace(self, **changes: Any) -> PearlConfig:
        return dataclasses.replace(self, **changes)
