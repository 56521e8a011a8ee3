"""A trained policy in your own code.

- `load_policy(run_dir)` (`policy`): the policy and encoder of a run folder, as a callable;
- `Adapter`, `Frame`, `Scene`, `observe` (`adapter`): the policy in a robot's control loop, from
  raw sensor arrays;
- `export_policy` (`export`) and `load_exported` (`exported`): a portable artifact (jax.export)
  and its loader, which imports neither flax nor this package's networks:
  `from mpcpearl_jax.deploy import load_exported` pulls in jax alone.

Every name is loaded on first use, so importing one never imports the others' dependencies.
"""

from typing import Any

__all__ = ["Adapter", "Frame", "Scene", "export_policy", "load_exported", "load_policy", "observe"]

_WHERE = {
    "Adapter": "adapter",
    "Frame": "adapter",
    "Scene": "adapter",
    "observe": "adapter",
    "export_policy": "export",
    "load_exported": "exported",
    "load_policy": "policy",
}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(f"mpcpearl_jax.deploy.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'mpcpearl_jax.deploy' has no attribute {name!r}")
