"""PEARL hyperparameters (method §7) as a frozen, validated dataclass."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

from mpcpearl_jax import validate as v
from mpcpearl_jax.errors import ConfigError

CROWD_ENCODERS = ("none", "attention", "deepsets", "sarl")
CROWD_STATIC = ("pool", "flat")
# the observation's parts a crowd encoder reads: each person's egocentric position, and the
# people's presence as the mask (`envs.observation.PARTS`)
CROWD_INPUTS = ("people_ego", "people_present")


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
    layer_norm: bool = False  # LayerNorm after every hidden layer of the Q and V networks
    # automatic entropy tuning (Haarnoja et al. 2018b, "SAC algorithms and applications"): the
    # entropy weight alpha of the actor loss and the V target (1 in the paper, whose temperature
    # is 1 / reward_scale) becomes a learned exp(log_alpha), starting at 1 (the paper's
    # temperature) and moved by Adam (lr) on -log_alpha (log pi + target entropy), so the
    # policy's entropy is pulled to the target; target_entropy None = -(action dimension)
    auto_entropy: bool = False
    target_entropy: float | None = None
    # a crowd encoder in front of the actor and the critics (`pearl.networks.CrowdEncoder`):
    # "none" (the paper: one MLP over the flat observation) or "attention" (each person and each
    # static obstacle embedded by a network shared within its kind, with the robot's own
    # features, and pooled by attention queried by the robot's state and goal, absent people
    # masked out, as crowd-navigation policies such as SARL do). "attention" needs the
    # observation's egocentric entries and presence (env.observe_relative, env.observe_presence)
    # "deepsets": the same entities embedded by one shared MLP each and pooled by their masked
    # mean and max (cheaper: no attention); "sarl": the same embeddings pooled by a softmax over
    # one learned score per person (SARL's attention, one head, no projections) and the max
    crowd_encoder: str = "none"
    crowd_dim: int = 64  # width of the per-entity embeddings and of each pooled feature
    crowd_heads: int = 4  # attention heads (crowd_dim must be a multiple; "attention" only)
    # the static obstacles (tables), fixed in number and order: "pool" (pooled as the people
    # are) or "flat" (their centres and nearest points as plain features beside the pools)
    crowd_static: str = "pool"
    # layers of the per-entity network of "deepsets" and "sarl" (1: one affine map and a ReLU
    # per person, the pooled features then read by the network's MLP)
    crowd_layers: int = 2
    # one crowd encoder shared by the twin critics and trained by their loss only; the policy
    # and V read its features with stopped gradients (as SAC-AE and DrQ do) and the target V
    # reads the target copy (an exponential average of it), so each observation is encoded
    # once per gradient step. false: the policy, each critic and V own an encoder
    crowd_shared: bool = False
    # the MPC as a teacher: the actor's loss adds `imitation` x a behaviour-cloning term toward
    # the MPC's action on the replay transitions the MPC acted on, kept where the critic rates
    # the MPC's action at least as high as the policy's (the Q-filter of Nair et al., ICRA
    # 2018), on the critic's scale (times the batch's mean |min Q|, as TD3+BC). 0 = off (the
    # paper)
    imitation: float = 0.0

    def __post_init__(self) -> None:
        v.ints(self, "latent_dim", "meta_batch", "batch_size", "context_size")
        v.int_tuples(self, "hidden", "encoder_hidden")
        v.positive(self, "lr", "reward_scale", "min_posterior_var")
        v.interval(self, "gamma", "tau", lo=0.0, hi=1.0)
        v.nonnegative(self, "kl_weight", "policy_mean_reg", "policy_std_reg")
        v.flags(self, "use_context", "layer_norm", "auto_entropy", "crowd_shared")
        v.nonnegative(self, "imitation")
        v.check(
            self.target_entropy is None or v.is_number(self.target_entropy),
            self,
            "target_entropy",
            "must be a number or null (= minus the action dimension)",
        )
        v.check(
            self.target_entropy is None or self.auto_entropy,
            self,
            "target_entropy",
            "only used with auto_entropy: set pearl.auto_entropy=true",
        )
        v.check(
            v.is_number(self.log_std_min)
            and v.is_number(self.log_std_max)
            and self.log_std_min < self.log_std_max,
            self,
            "log_std_min",
            "must be below log_std_max",
        )
        v.positive(self, "max_grad_norm", none_ok=True)
        v.check(
            self.crowd_encoder in CROWD_ENCODERS,
            self,
            "crowd_encoder",
            f"must be one of {', '.join(CROWD_ENCODERS)}, got {self.crowd_encoder!r}",
        )
        v.check(
            self.crowd_static in CROWD_STATIC,
            self,
            "crowd_static",
            f"must be one of {', '.join(CROWD_STATIC)}, got {self.crowd_static!r}",
        )
        v.ints(self, "crowd_dim", "crowd_heads", "crowd_layers")
        v.check(
            self.crowd_encoder != "attention" or self.crowd_dim % self.crowd_heads == 0,
            self,
            "crowd_dim",
            f"must be a multiple of crowd_heads ({self.crowd_heads}), got {self.crowd_dim}",
        )

    def replace(self, **changes: Any) -> PearlConfig:
        return dataclasses.replace(self, **changes)


def check_crowd_options(cfg: PearlConfig, missing: Sequence[str]) -> None:
    """ConfigError naming the env options `missing` that turn on the observation's parts a
    crowd encoder reads (`CROWD_INPUTS`; `envs.observation.missing_options` finds them);
    nothing without a crowd encoder or with none missing."""
    if cfg.crowd_encoder == "none" or not missing:
        return
    raise ConfigError(
        f"pearl.crowd_encoder={cfg.crowd_encoder} reads each person's egocentric position "
        f"and presence: set {' and '.join(f'env.{m}=true' for m in missing)}"
    )
