"""Every error type the package raises for a user to act on, in one place at the bottom of the
import graph (it imports nothing): configs, envs, data loaders, checkpoints and trainers raise
these, and command lines catch them without importing the layers that raise them."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration value is invalid; the message names the field."""


class DataFormatError(ValueError):
    """A data file (e.g. an ETH/UCY trajectory file) is malformed; the message names the file
    and the line."""


class CheckpointError(RuntimeError):
    """A checkpoint is missing, corrupt, or does not match the configuration."""


class TrainingDiverged(RuntimeError):
    """A loss became NaN/inf; the last good checkpoint is kept."""


class RunDirError(RuntimeError):
    """A run directory cannot be created or written (permissions, a full disk, an I/O error), or
    another process is writing it (`mpcpearl_jax.training.runlock`); the message names the
    folder."""


class WorkerPoolError(RuntimeError):
    """The MPC's worker pool cannot start (`mpc.pool`): the message says why and what to change
    (e.g. the main guard a spawned process needs, or `mpc.n_workers=1`)."""


__all__ = [
    "CheckpointError",
    "ConfigError",
    "DataFormatError",
    "RunDirError",
    "TrainingDiverged",
    "WorkerPoolError",
]
