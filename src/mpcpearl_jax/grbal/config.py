"""GrBAL hyperparameters and run configuration: frozen dataclasses validated at construction.

Defaults are the paper's GrBAL table (Adam, lr 1e-3, inner lr 1e-2, gamma 0.99, MPC horizon 10,
256 samples per minibatch, 3 x 256 ReLU, 4 samples per adaptation, 24 tasks per meta-batch); the
rest (planner samples, schedule) are this project's choices, documented in docs/grbal.md. A wrong
value raises `ConfigError` naming the field.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from mpcpearl_jax.config import SerializableConfig
from mpcpearl_jax.errors import ConfigError

ROBOT_MODELS = ("learned", "known")


def _check_pos_int(obj: Any, *fields: str) -> None:
    for f in fields:
        v = getattr(obj, f)
        if not (isinstance(v, int) and not isinstance(v, bool) and v > 0):
            raise ConfigError(f"{type(obj).__name__}.{f}: must be a positive int, got {v!r}")


def _check_number(obj: Any, field: str, lo: float, hi: float, open_lo: bool = False) -> None:
    v = getattr(obj, field)
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    ok = ok and (v > lo if open_lo else v >= lo) and v <= hi
    if not ok:
        bound = f"({lo}, {hi}]" if open_lo else f"[{lo}, {hi}]"
        raise ConfigError(f"{type(obj).__name__}.{field}: must lie in {bound}, got {v!r}")


@dataclasses.dataclass(frozen=True)
class GrbalConfig:
    """Model, meta-training, planner and schedule of GrBAL (Nagabandi et al., ICLR 2019)."""

    # ---- learned model f_theta(obs, action) -> next-obs delta (paper's GrBAL table)
    hidden: tuple[int, ...] = (256, 256, 256)
    lr: float = 1e-3  # outer Adam
    inner_lr: float = 1e-2  # one inner SGD step
    meta_batch: int = 24  # tasks per meta-batch
    windows: int = (
        256  # windows (M past + K future) per outer step; window i: task i mod meta_batch
    )
    past: int = 4  # M, samples per adaptation
    future: int = 4  # K, transitions the adapted model is scored on (K = M as in GrBAL's code)
    # ---- planner: MPPI on the adapted model
    gamma: float = 0.99  # discount of the stage costs over the planning horizon
    plan_horizon: int = 10
    num_samples: int = 256  # N action sequences per MPPI iteration
    mppi_iterations: int = 2
    temperature: float = 1.0  # lambda of the MPPI weights exp(-(J - J_min) / lambda)
    noise_std: float = 0.5  # MPPI sampling std in the normalized action box [-1, 1]^2
    # "learned": the model predicts everything (GrBAL); "known": the robot pose follows eq. (1)
    # and only the people come from the model
    robot_model: str = "learned"
    # ---- data collection
    explore_std: float = 0.1  # Gaussian noise on the executed action while collecting
    # rounds of random-action episodes (episodes_per_task each) over every training task before
    # the first fit
    initial_episodes: int = 1
    tasks_per_iteration: int = 8
    episodes_per_task: int = 1
    buffer_episodes: int = 20  # per-task buffer capacity, in episodes
    # ---- schedule
    iterations: int = 100
    updates_per_iteration: int = 200  # outer Adam steps between two collections
    eval_interval: int = 5  # iterations between test evaluations (0 = only at the end)
    eval_adapt_episodes: int = 2
    checkpoint_interval: int = 5
    keep_checkpoints: int = 3

    def __post_init__(self) -> None:
        n = type(self).__name__
        if not (
            isinstance(self.hidden, tuple)
            and len(self.hidden) > 0
            and all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in self.hidden)
        ):
            raise ConfigError(f"{n}.hidden: must be a non-empty tuple of positive ints")
        _check_pos_int(
            self,
            "meta_batch",
            "windows",
            "past",
            "future",
            "plan_horizon",
            "num_samples",
            "mppi_iterations",
            "initial_episodes",
            "tasks_per_iteration",
            "episodes_per_task",
            "buffer_episodes",
            "iterations",
            "updates_per_iteration",
            "eval_adapt_episodes",
            "checkpoint_interval",
            "keep_checkpoints",
        )
        if not (isinstance(self.eval_interval, int) and self.eval_interval >= 0):
            raise ConfigError(f"{n}.eval_interval: must be a non-negative int")
        _check_number(self, "lr", 0.0, 1.0, open_lo=True)
        _check_number(self, "inner_lr", 0.0, 10.0)
        _check_number(self, "gamma", 0.0, 1.0)
        _check_number(self, "temperature", 0.0, 1e6, open_lo=True)
        _check_number(self, "noise_std", 0.0, 10.0, open_lo=True)
        _check_number(self, "explore_std", 0.0, 10.0)
        if self.robot_model not in ROBOT_MODELS:
            raise ConfigError(f"{n}.robot_model: must be one of {ROBOT_MODELS}")
        if self.windows < self.meta_batch:
            raise ConfigError(f"{n}.windows: must be at least meta_batch ({self.meta_batch})")

    def replace(self, **changes: Any) -> GrbalConfig:
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class GrbalExperimentConfig(SerializableConfig):
    """Everything a GrBAL run needs; saved as config.json (resume checks it)."""

    env: str = "restaurant"
    seeds: int = 1
    seed: int = 0
    task_seed: int = 0
    grbal: GrbalConfig = GrbalConfig()
    env_overrides: dict = dataclasses.field(default_factory=dict)
    task_options: dict = dataclasses.field(default_factory=dict)
    data: str | None = None  # trajectory file (sidewalk)
    online_eval: bool = False  # online adaptation as the headline evaluation (sidewalk)
    method: str = "grbal"  # tells run readers (experiments.compare) what made the run

    def __post_init__(self) -> None:
        _check_pos_int(self, "seeds")
        for f in ("seed", "task_seed"):
            if not isinstance(getattr(self, f), int):
                raise ConfigError(f"GrbalExperimentConfig.{f}: must be an int")
        if not isinstance(self.grbal, GrbalConfig):
            raise ConfigError("GrbalExperimentConfig.grbal: must be a GrbalConfig")
        for f in ("env_overrides", "task_options"):
            if not isinstance(getattr(self, f), dict):
                raise ConfigError(f"GrbalExperimentConfig.{f}: must be a dict")
        if self.method != "grbal":
            raise ConfigError("GrbalExperimentConfig.method: must be 'grbal'")

    @classmethod
    def from_dict(cls, d: dict) -> GrbalExperimentConfig:
        d = dict(d)
        g = dict(d.pop("grbal", {}))
        if "hidden" in g:
            g["hidden"] = tuple(g["hidden"])
        return cls(grbal=GrbalConfig(**g), **d)


PRESETS: dict[str, GrbalConfig] = {
    # about a minute: the pipeline end to end
    "smoke": GrbalConfig(
        hidden=(32, 32),
        meta_batch=4,
        windows=16,
        num_samples=32,
        mppi_iterations=1,
        tasks_per_iteration=2,
        buffer_episodes=4,
        iterations=2,
        updates_per_iteration=5,
        eval_interval=1,
        checkpoint_interval=1,
    ),
    # a few minutes on a 2-core CPU
    "default": GrbalConfig(
        hidden=(128, 128, 128),
        windows=96,
        num_samples=128,
        mppi_iterations=1,
        iterations=6,
        updates_per_iteration=150,
        eval_interval=3,
        checkpoint_interval=3,
    ),
    # the CPU schedule (about a minute per iteration on a 2-core CPU); stop it any time
    "cpu": GrbalConfig(
        hidden=(128, 128, 128),
        windows=96,
        num_samples=128,
        mppi_iterations=1,
        iterations=1000,
        updates_per_iteration=300,
        eval_interval=10,
        checkpoint_interval=10,
    ),
    # the paper's GrBAL table, with this project's schedule
    "paper": GrbalConfig(),
}


def preset(name: str) -> GrbalConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown GrBAL preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name]
