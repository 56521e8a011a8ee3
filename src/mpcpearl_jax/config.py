"""Experiment configuration: frozen dataclasses with defaults in code, validated at construction.

`TrainConfig` is the meta-training schedule (method §7); `ExperimentConfig` ties env, PEARL, MPC and
schedule together. Presets live in `PRESETS`; a wrong value raises `ConfigError` naming the field.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, Self

from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.pearl.config import PearlConfig


def _pos_int(obj: Any, *fields: str) -> None:
    for f in fields:
        v = getattr(obj, f)
        if not (isinstance(v, int) and not isinstance(v, bool) and v > 0):
            raise ConfigError(f"{type(obj).__name__}.{f}: must be a positive int, got {v!r}")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Meta-training schedule (Algorithm 1; method §7 defaults)."""

    iterations: int = 3000
    initial_episodes: int = 3  # per training task at iteration 0, prior z (200 steps -> 3 x 80)
    tasks_per_iteration: int = 3
    prior_episodes: int = 3  # per visited task, prior z, RL + encoder buffers
    posterior_episodes: int = 3  # per visited task, posterior z, RL buffer only
    updates_per_iteration: int = 750  # N_train
    rl_capacity: int = 20_000  # transitions per task
    eps: float = 0.2  # MPC probability on an event (0 = PEARL)
    eval_interval: int = 10  # iterations between test evaluations (0 = only at the end)
    eval_adapt_episodes: int = 2
    t_update: int = 5  # online adaptation
    checkpoint_interval: int = 10
    keep_checkpoints: int = 3
    # ---- extensions beyond the paper (all off by default and in the `paper` preset; docs/
    # extensions.md describes and measures each one)
    # MPC warm start: a share of the collection rows is driven by the MPC on every step (not
    # only on events); the share starts at mpc_demo_share and falls linearly to 0 at iteration
    # mpc_demo_iterations (the initial collection is iteration 0), after which only the paper's
    # event-triggered infusion with probability eps remains.
    mpc_demo_share: float = 0.0
    mpc_demo_iterations: int = 0
    # in a warm-start row the MPC acts on each step with this probability and the stochastic
    # policy on the others (DAgger-style mixing: the MPC also acts from states the policy leads
    # to, so its transitions cover the policy's mistakes); 1 = the MPC drives the whole episode
    mpc_demo_step_prob: float = 1.0
    # MPC transitions kept apart: every transition the MPC produced (solved, not a fallback) is
    # also stored in a per-task MPC buffer of mpc_buffer_capacity, and this fraction of every
    # RL batch is drawn from it (symmetric sampling as in RLPD when 0.5).
    mpc_buffer_fraction: float = 0.0
    mpc_buffer_capacity: int = 4000
    # behaviours re-drawn: each time a training task is visited (after the initial collection),
    # its people get a fresh behaviour on the same table layout, so no crowd motion can be
    # learned by heart (domain randomization against the train/test gap); the task's buffers
    # keep their older transitions, its encoder buffer is refilled with the new behaviour
    redraw_behaviours: bool = False

    def __post_init__(self) -> None:
        _pos_int(
            self,
            "iterations",
            "initial_episodes",
            "tasks_per_iteration",
            "prior_episodes",
            "updates_per_iteration",
            "rl_capacity",
            "t_update",
            "checkpoint_interval",
            "keep_checkpoints",
            "eval_adapt_episodes",
        )
        for f in ("posterior_episodes", "eval_interval", "mpc_demo_iterations"):
            v = getattr(self, f)
            if not (isinstance(v, int) and v >= 0):
                raise ConfigError(f"TrainConfig.{f}: must be a non-negative int, got {v!r}")
        if not (
            isinstance(self.eps, (int, float))
            and not isinstance(self.eps, bool)
            and math.isfinite(self.eps)
            and 0.0 <= self.eps <= 1.0
        ):
            raise ConfigError(f"TrainConfig.eps: must lie in [0, 1], got {self.eps!r}")
        for f in ("mpc_demo_share", "mpc_buffer_fraction", "mpc_demo_step_prob"):
            v = getattr(self, f)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            if not (ok and 0.0 <= v <= 1.0):
                raise ConfigError(f"TrainConfig.{f}: must lie in [0, 1], got {v!r}")
        _pos_int(self, "mpc_buffer_capacity")
        if not isinstance(self.redraw_behaviours, bool):
            raise ConfigError(
                f"TrainConfig.redraw_behaviours: must be true or false, got "
                f"{self.redraw_behaviours!r}"
            )
        if self.mpc_buffer_fraction >= 1.0:
            raise ConfigError("TrainConfig.mpc_buffer_fraction: must be below 1")

    @property
    def uses_mpc(self) -> bool:
        """Whether collection calls the MPC: eps = 0 is PEARL, and then no extension that
        relies on MPC actions (warm start, MPC buffer, behaviour cloning) has anything to act on."""
        return self.eps > 0

    def demo_share(self, iteration: int) -> float:
        """Share of collection rows driven by the MPC (warm start) at `iteration`."""
        if self.mpc_demo_iterations <= 0 or not self.uses_mpc:
            return 0.0
        return self.mpc_demo_share * max(0.0, 1.0 - iteration / self.mpc_demo_iterations)


class SerializableConfig:
    """`replace`, `to_dict` and `to_json` of a frozen experiment-config dataclass (saved with
    its runs as config.json); each class adds its own `from_dict`."""

    def replace(self, **changes: Any) -> Self:
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)


@dataclasses.dataclass(frozen=True)
class ExperimentConfig(SerializableConfig):
    """Everything a run needs; `to_json`/`from_json` round-trip it (saved with checkpoints)."""

    env: str = "restaurant"
    seeds: int = 1
    seed: int = 0  # base seed of the run (seed s uses seed + s)
    task_seed: int = 0  # seed of the task sets
    pearl: PearlConfig = PearlConfig()
    train: TrainConfig = TrainConfig()
    mpc: dict = dataclasses.field(default_factory=dict)  # MPCConfig overrides
    env_overrides: dict = dataclasses.field(default_factory=dict)  # NavConfig overrides
    data: str | None = None  # data file for env families that read one (sidewalk)
    # options of the family's task builder, e.g. {"train_behaviours": 60} for the restaurant
    # (extension: more crowd behaviours per table layout in the training split; paper 15)
    task_options: dict = dataclasses.field(default_factory=dict)
    online_eval: bool = False  # report online adaptation as the headline evaluation
    # devices the seeds are split over (mpcpearl_jax.distributed); 0 = every device the seed
    # count divides evenly into. Per-seed results do not depend on it.
    devices: int = 0

    def __post_init__(self) -> None:
        _pos_int(self, "seeds")
        d = self.devices
        if not (isinstance(d, int) and not isinstance(d, bool) and d >= 0):
            raise ConfigError(f"ExperimentConfig.devices: must be a non-negative int, got {d!r}")
        if d and self.seeds % d:
            raise ConfigError(
                f"ExperimentConfig.devices: {self.seeds} seed(s) do not split evenly over {d} "
                "devices; give a seed count that is a multiple of it"
            )
        for f in ("seed", "task_seed"):
            if not isinstance(getattr(self, f), int):
                raise ConfigError(f"ExperimentConfig.{f}: must be an int")
        if not isinstance(self.task_options, dict):
            raise ConfigError("ExperimentConfig.task_options: must be a dict of builder options")
        if not isinstance(self.pearl, PearlConfig):
            raise ConfigError("ExperimentConfig.pearl: must be a PearlConfig")
        if not isinstance(self.train, TrainConfig):
            raise ConfigError("ExperimentConfig.train: must be a TrainConfig")
        if self.pearl.bc_weight > 0 and self.train.mpc_buffer_fraction == 0:
            raise ConfigError(
                "PearlConfig.bc_weight: behaviour cloning needs MPC samples in the batch "
                "(set train.mpc_buffer_fraction > 0)"
            )

    @classmethod
    def from_dict(cls, d: dict) -> ExperimentConfig:
        d = dict(d)
        pearl = dict(d.pop("pearl", {}))
        for f in ("hidden", "encoder_hidden"):
            if f in pearl:
                pearl[f] = tuple(pearl[f])
        return cls(pearl=PearlConfig(**pearl), train=TrainConfig(**d.pop("train", {})), **d)


def _small_pearl() -> PearlConfig:
    # reward_scale 5 (temperature 0.2) instead of the paper's 100 (0.01): Q values 20x smaller
    # are fitted within the few thousand gradient steps a CPU affords per hour.
    return PearlConfig(
        reward_scale=5.0,
        hidden=(128, 128, 128),
        encoder_hidden=(128, 128, 128),
        meta_batch=8,
        batch_size=128,
        context_size=64,
    )


def _extended(cfg: ExperimentConfig, demo_iterations: int) -> ExperimentConfig:
    """The extensions of docs/extensions.md switched on (MPC warm start with DAgger-style mixing,
    MPC buffer at half of every batch, behaviour cloning, LayerNorm critics, unsafe-plan
    recovery). With eps = 0 (PEARL) the MPC-based ones are inactive."""
    train = dataclasses.replace(
        cfg.train,
        mpc_demo_share=1.0,
        mpc_demo_iterations=demo_iterations,
        mpc_demo_step_prob=0.5,
        mpc_buffer_fraction=0.5,
    )
    pearl = cfg.pearl.replace(bc_weight=1.0, bc_q_filter=False, layer_norm=True)
    return cfg.replace(
        pearl=pearl, train=train, mpc={**cfg.mpc, "unsafe_recovery": True, "n_workers": 2}
    )


# the CPU schedule: 8 tasks x (1 prior + 1 posterior) episodes and 500 gradient steps per
# iteration (about 12 s on a 2-core CPU with the MPC warm start on)
_CPU_TRAIN = TrainConfig(
    iterations=3000,
    initial_episodes=1,
    tasks_per_iteration=8,
    prior_episodes=1,
    posterior_episodes=1,
    updates_per_iteration=500,
    rl_capacity=20_000,
    eval_interval=25,
    checkpoint_interval=25,
)

PRESETS: dict[str, ExperimentConfig] = {
    # a couple of minutes on a laptop CPU: proves the whole pipeline end to end
    "smoke": ExperimentConfig(
        pearl=PearlConfig(
            hidden=(64, 64), encoder_hidden=(64, 64), meta_batch=4, batch_size=64, context_size=32
        ),
        train=TrainConfig(
            iterations=4,
            initial_episodes=1,
            tasks_per_iteration=4,
            prior_episodes=1,
            posterior_episodes=1,
            updates_per_iteration=20,
            rl_capacity=2_000,
            eval_interval=2,
            checkpoint_interval=2,
        ),
    ),
    # the README's main command: a few minutes on a laptop CPU, extensions on
    "default": _extended(
        ExperimentConfig(
            pearl=_small_pearl(),
            train=dataclasses.replace(
                _CPU_TRAIN,
                iterations=16,
                rl_capacity=6_000,
                eval_interval=8,
                checkpoint_interval=8,
            ),
        ),
        demo_iterations=400,
    ),
    # the CPU schedule with the extensions (docs/extensions.md); stop it any time (--iterations)
    "cpu": _extended(ExperimentConfig(pearl=_small_pearl(), train=_CPU_TRAIN), 400),
    # the same CPU schedule and networks with the paper's algorithm (no extension)
    "cpu-paper": ExperimentConfig(pearl=_small_pearl(), train=_CPU_TRAIN),
    # method §7 exactly
    "paper": ExperimentConfig(pearl=PearlConfig(), train=TrainConfig()),
}


def preset(name: str) -> ExperimentConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name]
