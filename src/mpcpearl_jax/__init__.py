"""mpcpearl_jax: MPC-PEARL (meta-RL with event-triggered risk-aware MPC infusion) in JAX.

Public entry points: `make_env`, `make_tasks` (environments), `load_policy` (a trained policy
from a run directory), `metrics`; `Adapter`, `Frame`, `Scene`, `observe` (a policy in your own
control loop, from raw sensor arrays: `deploy`), `export_policy` and `load_exported` (a portable
artifact run with jax alone: `export`, `exported`); see the subpackages `envs`, `mpc`, `pearl`.
"""

from typing import Any

from mpcpearl_jax import metrics
from mpcpearl_jax.envs import make_env, make_tasks

__version__ = "0.1.0"

__all__ = [
    "Adapter",
    "Frame",
    "Scene",
    "export_policy",
    "load_exported",
    "load_policy",
    "make_env",
    "make_tasks",
    "metrics",
    "observe",
    "__version__",
]

# lazy: checkpointing and exporting pull in orbax
_LAZY = {
    "Adapter": "deploy",
    "Frame": "deploy",
    "Scene": "deploy",
    "observe": "deploy",
    "export_policy": "export",
    "load_exported": "exported",
}


def __getattr__(name: str) -> Any:
    if name == "load_policy":
        from mpcpearl_jax.policy import load_policy

        return load_policy
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"mpcpearl_jax.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'mpcpearl_jax' has no attribute {name!r}")
