"""PEARL (SAC + probabilistic context encoder) in JAX: networks, losses, buffers, learner.

Every name is loaded on first use: `pearl.config` (and so config validation) needs neither flax's
networks nor distrax nor optax.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
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

_LAZY = {
    "PearlConfig": "config",
    "LearnerState": "learner",
    "acting_params": "learner",
    "init_learner": "learner",
    "make_update": "learner",
    "Losses": "losses",
    "make_losses": "losses",
    "target_entropy": "losses",
    "Networks": "networks",
    "Transitions": "types",
    "context_from": "types",
}


def __getattr__(name: str) -> Any:
    import importlib

    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
