"""PEARL (SAC + probabilistic context encoder) in JAX: networks, losses, buffers, learner."""

from mpcpearl_jax.pearl.config import PearlConfig
from mpcpearl_jax.pearl.learner import (
    LearnerState,
    Transitions,
    context_from,
    init_learner,
    make_update_fn,
)
from mpcpearl_jax.pearl.networks import Networks

__all__ = [
    "LearnerState",
    "Networks",
    "PearlConfig",
    "Transitions",
    "context_from",
    "init_learner",
    "make_update_fn",
]
