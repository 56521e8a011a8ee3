"""mpcpearl_jax: MPC-PEARL (meta-RL with event-triggered risk-aware MPC infusion) in JAX.

Public entry points: `make_env`, `make_tasks` (environments), `load_policy` (a trained policy
from a run directory), `metrics`; see the subpackages `envs`, `mpc`, `pearl`.
"""

from typing import Any

from mpcpearl_jax import metrics
from mpcpearl_jax.envs import make_env, make_tasks

__version__ = "0.1.0"

__all__ = ["load_policy", "make_env", "make_tasks", "metrics", "__version__"]


def __getattr__(name: str) -> Any:  # lazy: checkpointing pulls in orbax
    if name == "load_policy":
        from mpcpearl_jax.checkpoint import load_policy

        return load_policy
    raise AttributeError(f"module 'mpcpearl_jax' has no attribute {name!r}")
