"""PEARL (SAC + probabilistic context encoder) in JAX: networks, losses, buffers, learner."""

from mpcpearl_jax.pearl.config import PearlConfig
from mpcpearl_jax.pearl.learner import (
    LearnerState,
    acting_params,
    init_learner,
    make_update,
)
from mpcpearl_jax.pearl.losses import Losses, make_losses, target_entropy
from mpcpearl_jax.pearl.networks import Networks
from mpcpearl_jax.pearl.types import Transitions, context_from

__all__ = [
    "LearnerState",
    "Losses",
    "Networks",
    "PearlConfig",
    "Transitions",
    "acting_params",
    "context_from",
    "init_learner",
    "make_losses",
    "make_update",
    "target_entropy",
]
