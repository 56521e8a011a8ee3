"""What the run session (`training.run.Session`), the training loop (`training.loop`), the
minutes mode (`training.budget`) and the end of a run (`training.final`) ask of a trainer: the
protocol that both MPC-PEARL's `training.trainer.Trainer` and GrBAL's `grbal.trainer.GrbalTrainer`
follow (`TrainerProtocol`), and the per-seed key split both use (`split_keys`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import jax
from jax import Array

from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.types import TaskParams


class TrainerProtocol(Protocol):
    """A trainer of S seeds side by side: its config, env and task sets; a fresh state
    (`init_state`), one iteration of its algorithm (`iteration`: collection and updates, a log
    row's fields; `stop()` may end the iteration early where it loses nothing) and the method §8
    metrics of a state (`evaluate`, on the test tasks by default, mean and per seed). A trainer
    with a `close()` (the MPC's worker pool) is closed with the session."""

    cfg: Any
    env: NavEnv
    train_tasks: TaskParams
    test_tasks: TaskParams
    horizon: int

    def init_state(self) -> Any: ...

    def iteration(self, state: Any, stop: Callable[[], bool] | None = None) -> tuple[Any, dict]: ...

    def evaluate(
        self,
        state: Any,
        tasks: TaskParams | None = None,
        online: bool = False,
        key: Array | None = None,
    ) -> dict: ...


def split_keys(keys: Array, n: int) -> tuple[Array, Array]:
    """keys [S, 2] -> (new carry keys [S, 2], subkeys [S, n, 2])."""
    both = jax.vmap(lambda k: jax.random.split(k, n + 1))(keys)
    return both[:, 0], both[:, 1:]
