"""`Trainer` under its earlier import path; the trainer lives in `mpcpearl_jax.training.trainer`."""

from mpcpearl_jax.training.trainer import IterationAbandoned, Trainer, TrainState

__all__ = ["IterationAbandoned", "TrainState", "Trainer"]
