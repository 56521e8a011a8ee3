"""GrBAL hyperparameters and run configuration: frozen dataclasses validated at construction.

Defaults are the paper's GrBAL table (Adam, lr 1e-3, inner lr 1e-2, gamma 0.99, MPC horizon 10,
256 samples per minibatch, 3 x 256 ReLU, 4 samples per adaptation, 24 tasks per meta-batch); the
rest (planner samples, schedule) are this project's choices, documented in docs/grbal.md. A wrong
value raises `ConfigError` naming the field.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Self

from mpcpearl_jax import validate as v
from mpcpearl_jax.config import SerializableConfig
from mpcpearl_jax.errors import ConfigError

ROBOT_MODELS = ("learned", "known")
# upper bounds of the planner's size fields: MPPI holds num_samples sequences of plan_horizon
# actions per env and step (the trainer also bounds plan_horizon by the episode length)
MAX_PLAN_HORIZON = 1000
MAX_SAMPLES = 65536


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
        v.int_tuples(self, "hidden")
        v.ints(
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
        v.ints(self, "eval_interval", lo=0)
        for name, top in (("plan_horizon", MAX_PLAN_HORIZON), ("num_samples", MAX_SAMPLES)):
            value = getattr(self, name)
            v.check(value <= top, self, name, f"must be at most {top}, got {value}")
        v.interval(self, "lr", lo=0.0, hi=1.0, open_lo=True)
        v.interval(self, "inner_lr", lo=0.0, hi=10.0)
        v.interval(self, "gamma", lo=0.0, hi=1.0)
        v.interval(self, "temperature", lo=0.0, hi=1e6, open_lo=True)
        v.interval(self, "noise_std", lo=0.0, hi=10.0, open_lo=True)
        v.interval(self, "explore_std", lo=0.0, hi=10.0)
        v.one_of(self, "robot_model", ROBOT_MODELS)
        v.check(
            self.windows >= self.meta_batch,
            self,
            "windows",
            f"must be at least meta_batch ({self.meta_batch})",
        )

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
    method: str = "grbal"  # tells run readers (lab.compare) what made the run

    def __post_init__(self) -> None:
        v.ints(self, "seeds")
        v.ints(self, "seed", "task_seed", lo=None)
        v.instance(self, "grbal", GrbalConfig, "a GrbalConfig")
        v.instance(self, "env_overrides", dict, "a dict")
        v.instance(self, "task_options", dict, "a dict")
        v.one_of(self, "method", ("grbal",))
        v.flags(self, "online_eval")

    @classmethod
    def from_preset(cls, name: str, env: str | None = None, *, scenarios: Any = None) -> Self:
        """GrBAL preset `name` on task family `env` (restaurant when None), with the family's
        headline protocol (`envs.online_eval`); `mpcpearl_jax.config.resolve` builds a run's
        config from it (the task source, the changes and --set on top)."""
        from mpcpearl_jax.envs import online_eval

        env = env or "restaurant"
        return cls(env=env, grbal=preset(name), online_eval=online_eval(env))

    @classmethod
    def from_dict(cls, d: dict) -> GrbalExperimentConfig:
        d = dict(d)
        g = dict(d.pop("grbal", {}))
        if "hidden" in g:
            g["hidden"] = tuple(g["hidden"])
        return cls(grbal=GrbalConfig(**g), **d)


# the CPU sizes of the `default` and `cpu` presets: 3 x 128 networks, 96 windows, one MPPI
# iteration of 128 samples
_CPU_SIZES: dict[str, Any] = dict(
    hidden=(128, 128, 128), windows=96, num_samples=128, mppi_iterations=1
)

# each preset as its differences from GrbalConfig's defaults (the paper's GrBAL table)
PRESET_CHANGES: dict[str, dict[str, Any]] = {
    # about a minute: the pipeline end to end
    "smoke": dict(
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
    "default": {
        **_CPU_SIZES,
        "iterations": 6,
        "updates_per_iteration": 150,
        "eval_interval": 3,
        "checkpoint_interval": 3,
    },
    # the CPU schedule (about a minute per iteration on a 2-core CPU); stop it any time
    "cpu": {
        **_CPU_SIZES,
        "iterations": 1000,
        "updates_per_iteration": 300,
        "eval_interval": 10,
        "checkpoint_interval": 10,
    },
    # the paper's GrBAL table, with this project's schedule
    "paper": {},
}

PRESETS: dict[str, GrbalConfig] = {
    name: GrbalConfig(**changes) for name, changes in PRESET_CHANGES.items()
}


def preset(name: str) -> GrbalConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown GrBAL preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name]
