"""The restaurant task family (method §3); registers itself with `mpcpearl_jax.envs`."""

from typing import Any

from mpcpearl_jax.envs import register
from mpcpearl_jax.envs.restaurant.generator import (
    TABLE_CONFIGS,
    CrowdModel,
    make_restaurant_tasks,
    redraw_train_tasks,
    simulate_crowd,
    table_layout,
)
from mpcpearl_jax.envs.restaurant.scenarios import (
    SCENARIO_OPTIONS,
    make_scenario_tasks,
    scenario_digests,
    scenario_options,
)
from mpcpearl_jax.envs.types import NavConfig, TaskParams

RESTAURANT_CONFIG = NavConfig(
    name="restaurant",
    dt=0.05,
    horizon=80,
    v_max=7.0,
    arena_lo=(-5.0, -5.0),
    arena_hi=(5.0, 5.0),
    observe_static=True,
)


def _builder(split: str, seed: int, config: NavConfig, **kwargs: Any) -> TaskParams:
    """The project's generated crowds, or with `scenarios=DIR` the paper's own scenarios
    (`scenarios.make_scenario_tasks`; the seed does not apply to them)."""
    if kwargs.get("scenarios"):
        unknown = set(kwargs) - SCENARIO_OPTIONS
        if unknown:
            raise TypeError(
                f"make_tasks('restaurant', scenarios=...) got options of the generated crowds "
                f"{sorted(unknown)} (the scenarios are fixed crowds)"
            )
        return make_scenario_tasks(split, config, **kwargs)
    unknown = set(kwargs) - {"train_behaviours"}
    if unknown:
        raise TypeError(f"make_tasks('restaurant') got unexpected arguments {sorted(unknown)}")
    return make_restaurant_tasks(split, seed, config, **kwargs)


register("restaurant", RESTAURANT_CONFIG, _builder, redraw=redraw_train_tasks)

__all__ = [
    "RESTAURANT_CONFIG",
    "TABLE_CONFIGS",
    "CrowdModel",
    "make_restaurant_tasks",
    "make_scenario_tasks",
    "redraw_train_tasks",
    "scenario_digests",
    "scenario_options",
    "simulate_crowd",
    "table_layout",
]
