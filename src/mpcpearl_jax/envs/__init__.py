"""Navigation environments: `make_env(name)` and `make_tasks(name, split, seed=0)`.

Task families register a config and a task builder here; see `register` to add your own.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.numpy_ref import NumpyNavEnv, task_to_numpy
from mpcpearl_jax.envs.types import ConfigError, EnvState, NavConfig, StepInfo, TaskParams

SPLITS = ("train", "test", "ood", "val")

# name -> (default config, task builder(split, seed, config, **kwargs) -> stacked TaskParams)
_REGISTRY: dict[str, tuple[NavConfig, Callable[..., TaskParams]]] = {}
# name -> redraw(seed, config, task_ids, stream, **kwargs) -> stacked TaskParams (optional)
_REDRAW: dict[str, Callable[..., TaskParams]] = {}


def register(
    name: str,
    config: NavConfig,
    builder: Callable[..., TaskParams],
    redraw: Callable[..., TaskParams] | None = None,
) -> None:
    """Register a task family so that `make_env(name)` and `make_tasks(name, ...)` know it.

    `redraw(seed, config, task_ids, stream, **kwargs)`, optional, returns the training tasks
    `task_ids` with their people's behaviour drawn anew from the random stream `stream` (a tuple
    of ints); it backs the `TrainConfig.redraw_behaviours` extension."""
    _REGISTRY[name] = (config, builder)
    if redraw is not None:
        _REDRAW[name] = redraw
    else:
        _REDRAW.pop(name, None)


def can_redraw(name: str) -> bool:
    """Whether the task family can redraw its training behaviours."""
    return name in _REDRAW


def redraw_tasks(
    name: str,
    seed: int,
    task_ids: Any,
    stream: tuple[int, ...],
    config: NavConfig | None = None,
    **kwargs: Any,
) -> TaskParams:
    """Training tasks `task_ids` of family `name` with fresh behaviours (see `register`)."""
    default, _ = _lookup(name)
    if name not in _REDRAW:
        raise ConfigError(f"env {name!r} cannot redraw its training behaviours")
    return _REDRAW[name](seed, config or default, task_ids, stream, **kwargs)


def _lookup(name: str) -> tuple[NavConfig, Callable[..., TaskParams]]:
    if name not in _REGISTRY:
        raise ValueError(f"unknown env name {name!r}; known: {sorted(_REGISTRY)}")
    return _REGISTRY[name]


def env_names() -> list[str]:
    return sorted(_REGISTRY)


def make_env(name: str, **overrides: Any) -> NavEnv:
    """The environment of a task family; keyword overrides replace `NavConfig` fields."""
    config, _ = _lookup(name)
    unknown = set(overrides) - set(NavConfig.__dataclass_fields__)
    if unknown:
        raise ConfigError(f"NavConfig has no field(s) {sorted(unknown)}")
    return NavEnv(config.replace(**overrides) if overrides else config)


def make_tasks(
    name: str, split: str, seed: int = 0, config: NavConfig | None = None, **kwargs: Any
) -> TaskParams:
    """Tasks of a split stacked on a leading axis. split in {"train", "test", "ood"}."""
    default, builder = _lookup(name)
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r} for env {name!r}; expected one of {SPLITS}")
    return builder(split, seed, config or default, **kwargs)


def _restaurant_builder(split: str, seed: int, config: NavConfig, **kwargs: Any) -> TaskParams:
    from mpcpearl_jax.envs.restaurant import make_restaurant_tasks

    unknown = set(kwargs) - {"train_behaviours"}
    if unknown:
        raise TypeError(f"make_tasks('restaurant') got unexpected arguments {sorted(unknown)}")
    return make_restaurant_tasks(split, seed, config, **kwargs)


def _restaurant_redraw(
    seed: int, config: NavConfig, task_ids: Any, stream: tuple[int, ...], **kwargs: Any
) -> TaskParams:
    from mpcpearl_jax.envs.restaurant import redraw_train_tasks

    return redraw_train_tasks(seed, config, task_ids, stream, **kwargs)


def _register_builtin() -> None:
    from mpcpearl_jax.envs.restaurant import RESTAURANT_CONFIG

    register("restaurant", RESTAURANT_CONFIG, _restaurant_builder, _restaurant_redraw)
    try:  # the sidewalk family registers itself when present
        from mpcpearl_jax.envs import sidewalk  # noqa: F401
    except ImportError:
        pass


_register_builtin()

_LAZY = {"BraxNavEnv": "brax_adapter"}  # brax is imported only when the adapter is used


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "SPLITS",
    "BraxNavEnv",
    "ConfigError",
    "EnvState",
    "NavConfig",
    "NavEnv",
    "NumpyNavEnv",
    "StepInfo",
    "TaskParams",
    "can_redraw",
    "env_names",
    "make_env",
    "make_tasks",
    "redraw_tasks",
    "register",
    "task_to_numpy",
]
