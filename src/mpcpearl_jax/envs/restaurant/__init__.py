"""The restaurant task family (method §3)."""

from mpcpearl_jax.envs.restaurant.generator import (
    TABLE_CONFIGS,
    CrowdModel,
    make_restaurant_tasks,
    redraw_train_tasks,
    simulate_crowd,
    table_layout,
)
from mpcpearl_jax.envs.types import NavConfig

RESTAURANT_CONFIG = NavConfig(
    name="restaurant",
    dt=0.05,
    horizon=80,
    v_max=7.0,
    arena_lo=(-5.0, -5.0),
    arena_hi=(5.0, 5.0),
    observe_static=True,
)

__all__ = [
    "RESTAURANT_CONFIG",
    "TABLE_CONFIGS",
    "CrowdModel",
    "make_restaurant_tasks",
    "redraw_train_tasks",
    "simulate_crowd",
    "table_layout",
]
