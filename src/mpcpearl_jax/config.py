"""Experiment configuration: frozen dataclasses with defaults in code, validated at construction.

`TrainConfig` is the meta-training schedule (method §7); `ExperimentConfig` ties env, PEARL, MPC and
schedule together. Presets live in `PRESETS`; a wrong value raises `ConfigError` naming the field.
"""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Self, TypeVar

from mpcpearl_jax import validate as v
from mpcpearl_jax.envs.types import NavConfig
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.mpc.config import MPCConfig
from mpcpearl_jax.pearl.config import CROWD_INPUTS, PearlConfig, check_crowd_options

NAV_FIELDS = frozenset(f.name for f in dataclasses.fields(NavConfig))
# fields --set does not change, by class name: what chooses them instead
CHOSEN_ELSEWHERE: dict[str, dict[str, str]] = {
    "NavConfig": {"name": "the task family: choose it with --env"},
    "ExperimentConfig": {"env": "the task family: choose it with --env"},
    "GrbalExperimentConfig": {"env": "the task family: choose it with --env"},
}


def chosen_elsewhere(cls: type, field: str) -> str | None:
    """What chooses `cls.field` where --set does not (`CHOSEN_ELSEWHERE`), or None."""
    return CHOSEN_ELSEWHERE.get(cls.__name__, {}).get(field)


C = TypeVar("C")  # a run-config dataclass (ExperimentConfig, GrbalExperimentConfig)


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
    # behaviours re-drawn: each time a training task is visited (after the initial collection),
    # its people get a fresh behaviour on the same table layout, so no crowd motion can be
    # learned by heart (domain randomization against the train/test gap); the task's buffers
    # keep their older transitions, its encoder buffer is refilled with the new behaviour
    redraw_behaviours: bool = False
    # exploring starts: this share of the posterior-phase collection rows (the episodes that go
    # to the RL buffer only) starts at a random free pose of the arena instead of the task's
    # start, so the critic sees the goal and the ways round the tables early; the encoder's
    # context episodes and every evaluation start from the task's start as in the paper
    explore_start_share: float = 0.0
    # randomised crowd timing: each time a training task is visited (after the initial
    # collection), every one of its people waits an independent uniform number of steps in
    # {0, ..., crowd_delay_max} at its start before following its path (envs.perturb.
    # delay_people), drawn afresh per visit, so no timetable of the crowd can be learned by
    # heart; the task's own paths are kept (0 = off, the paper)
    crowd_delay_max: int = 0
    # ---- a schedule of the work, not of the algorithm's values (off in `paper`: Algorithm 1 as
    # printed; docs/usage.md, "Pipelined iterations"): the episodes of iteration k + 1 are
    # collected while the gradient steps of iteration k run, by the policy and encoder as they
    # were before those steps, so the acting policy lags one iteration behind the learner
    pipeline: bool = False

    def __post_init__(self) -> None:
        v.ints(
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
        v.ints(
            self,
            "posterior_episodes",
            "eval_interval",
            "crowd_delay_max",
            lo=0,
        )
        v.interval(
            self,
            "eps",
            "explore_start_share",
            lo=0.0,
            hi=1.0,
        )
        v.flags(self, "redraw_behaviours", "pipeline")
        v.check(
            self.explore_start_share < 1.0,
            self,
            "explore_start_share",
            "must be below 1 (the training statistics read the rows that start at the task's "
            "start)",
        )
        if self.explore_start_share > 0:
            v.check(
                self.posterior_episodes > 0,
                self,
                "explore_start_share",
                "exploring starts apply to the posterior-phase episodes: set "
                "posterior_episodes > 0",
            )

    @property
    def uses_mpc(self) -> bool:
        """Whether collection calls the MPC: eps = 0 is PEARL."""
        return self.eps > 0


class SerializableConfig:
    """`replace`, `to_dict` and `to_json` of a frozen experiment-config dataclass (saved with
    its runs as config.json); each class adds its own `from_dict`."""

    def replace(self, **changes: Any) -> Self:
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> Self:
        return cls.from_dict(json.loads(text))  # type: ignore[attr-defined]

    def validated(self) -> Self:
        """The checks across fields (`resolve` runs them last); none by default."""
        return self


@dataclasses.dataclass(frozen=True)
class ExperimentConfig(SerializableConfig):
    """Everything a run needs; `to_json`/`from_json` round-trip it (saved with checkpoints)."""

    env: str = "restaurant"
    seeds: int = 1
    seed: int = 0  # base seed of the run (seed s uses seed + s)
    task_seed: int = 0  # seed of the task sets
    pearl: PearlConfig = PearlConfig()
    train: TrainConfig = TrainConfig()
    # the MPC's settings; a dict of MPCConfig fields is accepted too (and converted)
    mpc: MPCConfig = MPCConfig()
    env_overrides: dict = dataclasses.field(default_factory=dict)  # NavConfig fields to change
    data: str | None = None  # data file for env families that read one (sidewalk)
    # options of the family's task builder, e.g. {"train_behaviours": 60} for the restaurant
    # (extension: more crowd behaviours per table layout in the training split; paper 15)
    task_options: dict = dataclasses.field(default_factory=dict)
    online_eval: bool = False  # report online adaptation as the headline evaluation
    # devices the seeds are split over (mpcpearl_jax.distributed); 0 = every device the seed
    # count divides evenly into. Per-seed results do not depend on it.
    devices: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.mpc, dict):  # e.g. config.json, or replace(mpc={...})
            object.__setattr__(self, "mpc", mpc_config(self.mpc))
        v.ints(self, "seeds")
        v.ints(self, "devices", lo=0)
        v.ints(self, "seed", "task_seed", lo=0)
        # the seeds' PRNG keys and host streams take 64-bit seeds: seed s uses seed + s
        top = 2**63 - self.seeds
        v.check(self.seed <= top, self, "seed", f"must be at most {top}, got {self.seed}")
        v.check(self.task_seed < 2**63, self, "task_seed", "must be below 2**63")
        v.instance(self, "env", str, "a task family name")
        v.instance(self, "task_options", dict, "a dict of builder options")
        v.instance(self, "pearl", PearlConfig, "a PearlConfig")
        v.instance(self, "train", TrainConfig, "a TrainConfig")
        v.instance(self, "mpc", MPCConfig, "an MPCConfig")
        v.instance(self, "env_overrides", dict, "a dict of NavConfig fields")
        unknown = sorted(set(self.env_overrides) - NAV_FIELDS)
        v.check(not unknown, self, "env_overrides", f"NavConfig has no field(s) {unknown}")
        v.check(
            "name" not in self.env_overrides,
            self,
            "env_overrides",
            "'name' is the task family, the config's env (--env), not an override",
        )
        v.instance(self, "data", (str, type(None)), "a file path or None")
        v.flags(self, "online_eval")

    @classmethod
    def from_preset(cls, name: str, env: str | None = None, *, scenarios: Any = None) -> Self:
        """Preset `name` on task family `env` (the preset's when None) with the family's
        settings (`resolve`): the `default` preset re-draws crowds only where the family can
        (`envs.can_redraw`) and never on the paper's scenarios (a recorded crowd is kept), the
        family's MPC defaults (`envs.mpc_defaults`) and its headline protocol
        (`envs.online_eval`)."""
        from mpcpearl_jax.envs import can_redraw, mpc_defaults, online_eval

        cfg = preset(name)
        env = env or cfg.env
        if name == "default" and (scenarios is not None or not can_redraw(env)):
            cfg = cfg.replace(train=dataclasses.replace(cfg.train, redraw_behaviours=False))
        return cfg.replace(  # type: ignore[return-value]
            env=env,
            mpc=cfg.mpc.replace(**mpc_defaults(env)),
            online_eval=cfg.online_eval or online_eval(env),
        )

    def validated(self) -> Self:
        """`validate`: the checks across fields."""
        return validate(self)  # type: ignore[return-value]

    @classmethod
    def from_dict(cls, d: dict) -> ExperimentConfig:
        """The config of a dict (config.json). Options since removed (`REMOVED_OPTIONS`) are
        dropped: at their off value they changed nothing; switched on, they shaped only how the
        run trained, never the policy's inputs or networks, so the policy still loads and
        evaluates (`removed_options_on` names them; resuming such a run is refused)."""
        d = _without_removed(d)
        pearl = dict(known_fields(PearlConfig, d.pop("pearl", {})))
        for f in ("hidden", "encoder_hidden"):
            if f in pearl:
                pearl[f] = tuple(pearl[f])
        return cls(
            pearl=PearlConfig(**pearl),
            train=TrainConfig(**known_fields(TrainConfig, d.pop("train", {}))),
            mpc=mpc_config(d.pop("mpc", {})),
            **known_fields(cls, d),
        )


# Fields that choose where a run computes, never what: the devices its seeds are split over
# (per-seed results do not depend on it) and the MPC's worker processes (each row's solve
# depends only on its own problem and warm start, never on the worker that solves it or what
# that worker solved before: tests/test_worker_count.py). A run resumes, and a committed run's
# config is rebuilt, with them changed (`training.checkpoint.config_differences`).
RESULT_NEUTRAL: tuple[str, ...] = ("devices", "mpc.n_workers")


# Options removed after they measured no gain (docs/extensions.md, "Removed options"), with
# their off value: section -> {field: off value}. Every one of them acted on training only
# (what the critics learned; `keep_best`, which of the trained policies was saved; the MPC's
# `solver`, where the MPC's plans were solved), never on the policy's inputs or networks.
REMOVED_OPTIONS: dict[str, dict[str, Any]] = {
    "train": {
        "mpc_dagger_labels": False,
        "mpc_demo_share": 0.0,
        "mpc_demo_iterations": 0,
        "mpc_demo_step_prob": 1.0,
        "mpc_buffer_fraction": 0.0,
        "mpc_buffer_capacity": 4000,
        "keep_best": False,
        "keep_interval": 5,
        "keep_tasks": 16,
        "guide_share": 0.0,
        "guide_steps": 80,
        "guide_decrement": 8,
        "guide_success": 0.5,
        "guide_window": 0,
    },
    "pearl": {
        "policy_ema": 0.0,
        "alpha_lr": None,
        "bc_weight": 0.0,
        "bc_q_filter": True,
        "init_alpha": 1.0,
        "n_step": 1,
        "crossq": False,
        "crossq_momentum": 0.99,
    },
    "env_overrides": {"w_collision": 0.0},
    # the SQP in JAX on the device ("device"), beside the host's OSQP ("osqp", what remains)
    "mpc": {"solver": "osqp", "device_qp_iters": 30},
}
# Removed options that acted only together with others: 'section.field' -> the options, with
# their off value, that must all differ from it for this one to have changed training. The MPC
# warm start ran only with a share and an iteration count above 0 and with the MPC (eps > 0);
# its step probability and the cloning's Q filter qualified an option that had to be on, and
# cloning read the MPC buffer's rows. The MPC buffer held MPC transitions only (eps > 0), its
# capacity acted only with a fraction above 0, the kept policy's interval and task count only
# with `keep_best`, the CrossQ momentum only with CrossQ, the guide's roll-in steps, decrement,
# success threshold and evidence window only with a guide share. So the inactive values the
# presets carried (step probability 0.5, no Q filter, an MPC buffer fraction with eps 0, the
# guide's defaults) leave a committed run resumable. The MPC's solver acted only where the MPC
# did (eps > 0), the device solver's QP iterations only with the device solver.
_ACTIVE_ONLY_WITH: dict[str, dict[str, Any]] = {
    "train.mpc_demo_share": {"train.mpc_demo_iterations": 0, "train.eps": 0.0},
    "train.mpc_demo_iterations": {"train.mpc_demo_share": 0.0, "train.eps": 0.0},
    "train.mpc_demo_step_prob": {
        "train.mpc_demo_share": 0.0,
        "train.mpc_demo_iterations": 0,
        "train.eps": 0.0,
    },
    "pearl.bc_weight": {"train.mpc_buffer_fraction": 0.0, "train.eps": 0.0},
    "pearl.bc_q_filter": {
        "pearl.bc_weight": 0.0,
        "train.mpc_buffer_fraction": 0.0,
        "train.eps": 0.0,
    },
    "train.mpc_buffer_fraction": {"train.eps": 0.0},
    "train.mpc_buffer_capacity": {"train.mpc_buffer_fraction": 0.0, "train.eps": 0.0},
    "train.keep_interval": {"train.keep_best": False},
    "train.keep_tasks": {"train.keep_best": False},
    "pearl.crossq_momentum": {"pearl.crossq": False},
    "train.guide_steps": {"train.guide_share": 0.0},
    "train.guide_decrement": {"train.guide_share": 0.0},
    "train.guide_success": {"train.guide_share": 0.0},
    "train.guide_window": {"train.guide_share": 0.0},
    "mpc.solver": {"train.eps": 0.0},
    "mpc.device_qp_iters": {"mpc.solver": "osqp", "train.eps": 0.0},
}


def removed_options_on(d: dict) -> list[str]:
    """The removed options (`REMOVED_OPTIONS`) a config dict switches on, as 'section.field':
    set to another value than their off value, and, for those that acted only together with
    others (`_ACTIVE_ONLY_WITH`), with every one of those on too."""
    on = []
    for section, fields in REMOVED_OPTIONS.items():
        part = d.get(section) or {}
        for field, off in fields.items():
            name = f"{section}.{field}"
            needs = _ACTIVE_ONLY_WITH.get(name, {})
            if part.get(field, off) != off and all(
                _recorded(d, other) != value for other, value in needs.items()
            ):
                on.append(name)
    return on


def _recorded(d: dict, name: str) -> Any:
    """The value of 'section.field' in a config dict: as recorded, else its default (a removed
    option's off value)."""
    section, field = name.split(".")
    part = d.get(section) or {}
    if field in part:
        return part[field]
    if field in REMOVED_OPTIONS.get(section, {}):
        return REMOVED_OPTIONS[section][field]
    defaults = {"train": TrainConfig(), "pearl": PearlConfig(), "mpc": MPCConfig()}[section]
    return getattr(defaults, field)


def _without_removed(d: dict) -> dict:
    d = dict(d)
    for section, fields in REMOVED_OPTIONS.items():
        if isinstance(d.get(section), dict):
            d[section] = {k: v for k, v in d[section].items() if k not in fields}
    return d


def validate(cfg: ExperimentConfig) -> ExperimentConfig:
    """Every check of a config that involves more than one field, run once, where the config is
    resolved (`resolve`, which every command builds its config with), before a command touches
    anything; a config built by hand is checked by calling it (the session and the trainer take
    a checked config). The type and range of each single field
    are the dataclasses' own invariants, checked when a section is built (`__post_init__`,
    through `mpcpearl_jax.validate`); here: the seeds split evenly over the devices, the env
    overrides' values on the family's own NavConfig, and whether the family can re-draw its
    training crowds when `train.redraw_behaviours` asks for it (not the sidewalk's recorded
    windows, not the paper's fixed scenarios). Returns `cfg`; ConfigError naming the field."""
    from mpcpearl_jax.envs import can_redraw, make_env, observation

    if cfg.devices and cfg.seeds % cfg.devices:
        v.fail(
            cfg,
            "devices",
            f"{cfg.seeds} seed(s) do not split evenly over {cfg.devices} devices; give a "
            "seed count that is a multiple of it",
        )
    try:
        env = make_env(cfg.env, **cfg.env_overrides)
    except ValueError as e:
        msg = str(e) if isinstance(e, ConfigError) else f"ExperimentConfig.env: {e}"
        raise ConfigError(msg) from e
    on = [p.name for p in observation.parts(env.config)]
    check_crowd_options(cfg.pearl, observation.missing_options(on, CROWD_INPUTS))
    if cfg.pearl.imitation > 0 and not cfg.train.uses_mpc:
        v.fail(
            cfg.pearl,
            "imitation",
            f"imitates the MPC's actions, and train.eps={cfg.train.eps:g} never calls the MPC: "
            "set train.eps above 0 or pearl.imitation=0",
        )
    if cfg.train.redraw_behaviours and not can_redraw(cfg.env):
        raise ConfigError(
            f"TrainConfig.redraw_behaviours: env {cfg.env!r} cannot redraw its training "
            "behaviours (add --set train.redraw_behaviours=false)"
        )
    if cfg.train.redraw_behaviours and cfg.task_options.get("scenarios"):
        raise ConfigError(
            "TrainConfig.redraw_behaviours: the paper's scenarios are fixed crowds and cannot be "
            "re-drawn (add --set train.redraw_behaviours=false)"
        )
    return cfg


def known_fields(cls: type, fields: dict) -> dict:
    """`fields`, a dict of the dataclass `cls`'s fields; ConfigError naming any unknown one, in
    the words of `--set`."""
    unknown = sorted(set(fields) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ConfigError(f"{cls.__name__} has no field(s) {unknown}{_removed_note(cls, unknown)}")
    return fields


def _removed_note(cls: type, fields: Iterable[str]) -> str:
    """' (removed; see ...)' where one of `cls`'s fields is a removed option
    (`REMOVED_OPTIONS`), else ''."""
    sections = {
        TrainConfig: "train",
        PearlConfig: "pearl",
        MPCConfig: "mpc",
        NavConfig: "env_overrides",
    }
    fields = list(fields)
    gone = [f for f in fields if f in REMOVED_OPTIONS.get(sections.get(cls, ""), {})]
    if not gone:
        return ""
    names = "" if gone == fields else f"{', '.join(gone)}: "
    return f" ({names}removed; see docs/extensions.md, Removed options)"


def mpc_config(fields: dict) -> MPCConfig:
    """An MPCConfig from a dict of its fields (the defaults for the others); ConfigError naming
    any unknown field."""
    return MPCConfig(**known_fields(MPCConfig, fields))


# ------------------------------------------------------------------------------ presets
# Every preset is the paper's configuration (method §7: `PearlConfig()`, `TrainConfig()`,
# `MPCConfig()`) with the differences listed here, section by section, in one place. The blocks
# below are shared by several presets; docs/extensions.md describes each option and
# results/README.md measures it.

# the CPU networks and batches; reward_scale 5 (temperature 0.2) instead of the paper's 100
# (0.01): Q values 20x smaller are fitted within the few thousand gradient steps a CPU affords
# per hour
_CPU_NETS: dict[str, Any] = dict(
    reward_scale=5.0,
    hidden=(128, 128, 128),
    encoder_hidden=(128, 128, 128),
    meta_batch=8,
    batch_size=128,
    context_size=64,
)
# the CPU schedule: 8 tasks x (1 prior + 1 posterior) episodes and 500 gradient steps per
# iteration
_CPU_SCHEDULE: dict[str, Any] = dict(
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
# the observation options chosen on the restaurant's validation split: people's velocities,
# 3 m sensing range, the clock, egocentric entries, people listed nearest first
_OBSERVATION: dict[str, Any] = dict(
    observe_velocity=True,
    sensing_radius=3.0,
    observe_time=True,
    observe_relative=True,
    observe_sorted=True,
)
# the expert of every preset with the extensions (`smoke`, like `paper`, runs the SQP to
# convergence from one start), chosen on the convergence curve and the expert screen
# (docs/method.md §6, `python -m lab.convergence`, `lab/screens/expert.json`): at most 2 QPs
# (step tolerance 0.05, 3 line-search steps) and the unsafe-plan recovery. On the authors' 180
# training scenarios GP-MPC with 5 QPs cannot be told apart from it (+0.011 +- 0.024 SR) at twice
# the solve, and learners trained with 5 QPs scored lower on validation at equal iterations
_EXPERT: dict[str, Any] = dict(
    sqp_iters=2, sqp_step_tol=0.05, line_search_steps=3, unsafe_recovery=True
)
# the expert, its rows solved by one host process per core (at most 8; `RESULT_NEUTRAL`: the
# committed runs of these presets were trained with 2, to the same results)
_MPC_RECOVERY: dict[str, Any] = dict(_EXPERT, n_workers=0)

# name -> {section: {field: value}}: the differences from `paper`
PRESET_CHANGES: dict[str, dict[str, dict[str, Any]]] = {
    # method §7 exactly
    "paper": {},
    # a couple of minutes on a laptop CPU: proves the whole pipeline end to end
    "smoke": {
        "pearl": dict(
            hidden=(64, 64), encoder_hidden=(64, 64), meta_batch=4, batch_size=64, context_size=32
        ),
        "train": dict(
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
    },
    # the CPU schedule and networks with the options chosen on the validation split (results/
    # README.md): the paper's event-triggered infusion, LayerNorm critics, re-drawn crowds, the
    # observation options and exploring starts on half the posterior-phase episodes; restaurant
    # only (the sidewalk cannot re-draw its crowds: add --set train.redraw_behaviours=false
    # there). `--set train.crowd_delay_max=20` is the former `cpu-robust`
    "cpu-explore": {
        "pearl": {**_CPU_NETS, "layer_norm": True},
        "train": {**_CPU_SCHEDULE, "redraw_behaviours": True, "explore_start_share": 0.5},
        "mpc": _MPC_RECOVERY,
        "env_overrides": _OBSERVATION,
    },
    # the recommended recipe, trained on a time budget (`--minutes 24` on a 2-core CPU: the
    # five-seed comparison of results/README.md): `cpu-explore` with automatic entropy tuning,
    # exactly the former `cpu-auto` preset and `--preset cpu-explore --set
    # pearl.auto_entropy=true`
    "recipe": {
        "pearl": {**_CPU_NETS, "layer_norm": True, "auto_entropy": True},
        "train": {**_CPU_SCHEDULE, "redraw_behaviours": True, "explore_start_share": 0.5},
        "mpc": _MPC_RECOVERY,
        "env_overrides": _OBSERVATION,
    },
    # the README's main command, about five minutes on a 2-core CPU: `cpu-explore` with 2 x 64
    # networks, 4 tasks per gradient step (a step ~4x cheaper), automatic entropy tuning and 75
    # iterations; chosen on the validation split at a 5-minute budget (results/README.md)
    "default": {
        "pearl": {
            **_CPU_NETS,
            "hidden": (64, 64),
            "encoder_hidden": (64, 64),
            "meta_batch": 4,
            "auto_entropy": True,
            "layer_norm": True,
        },
        "train": {
            **_CPU_SCHEDULE,
            "iterations": 75,
            "redraw_behaviours": True,
            "explore_start_share": 0.5,
        },
        "mpc": _MPC_RECOVERY,
        "env_overrides": _OBSERVATION,
    },
}


def _build_preset(changes: dict[str, dict[str, Any]]) -> ExperimentConfig:
    return ExperimentConfig(
        pearl=PearlConfig(**changes.get("pearl", {})),
        train=TrainConfig(**changes.get("train", {})),
        mpc=MPCConfig(**changes.get("mpc", {})),
        env_overrides=dict(changes.get("env_overrides", {})),
    )


PRESETS: dict[str, ExperimentConfig] = {
    name: _build_preset(changes) for name, changes in PRESET_CHANGES.items()
}


# presets since removed -> how to build what they built
REMOVED_PRESETS: dict[str, str] = {
    "cpu-paper": "the paper's algorithm on the CPU schedule: start from a run that used it, "
    "--config results/restaurant/mpc-pearl-eps0.2-paper/config.json",
}


def preset(name: str) -> ExperimentConfig:
    if name in REMOVED_PRESETS:
        raise ConfigError(f"preset {name!r} was removed ({REMOVED_PRESETS[name]})")
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name]


# ---------------------------------------------------------------------- resolving a run's config
# What every command line builds its config with: a preset (or a run's recorded config.json),
# the task family's own settings, the task source and the command line's changes (typed values
# or `--set SECTION.FIELD=VALUE` strings, read by each field's type), for every algorithm's
# run-config class (`resolve`'s `config_type`).

_TRUE, _FALSE = ("true", "True", "1"), ("false", "False", "0")


def override_sections(cls: type) -> dict[str, type]:
    """The `--set` sections of a run-config dataclass (`ExperimentConfig`,
    `GrbalExperimentConfig`): each nested config by its field name, 'env' for the NavConfig
    fields of `env_overrides`, '' for the top-level fields."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    sections = {n: hints[n] for n in names if dataclasses.is_dataclass(hints[n])}
    if "env_overrides" in names:
        sections["env"] = NavConfig
    return {**sections, "": cls}


def field_value(item: str, cls: type, field: str, text: str) -> Any:
    """The value of `--set item` for `cls.field`, read by the field's type: booleans (true/false,
    True/False, 1/0) only for bool fields and never for numbers, None/null for optional fields,
    JSON otherwise (a list becomes a tuple; text that is not JSON stays a string). ConfigError
    naming the field."""
    hints = typing.get_type_hints(cls)
    if field not in hints or field not in {f.name for f in dataclasses.fields(cls)}:
        note = _removed_note(cls, [field])
        raise ConfigError(f"--set {item}: {cls.__name__} has no field(s) {[field]}{note}")
    name = f"{cls.__name__}.{field}"
    if chosen_elsewhere(cls, field):
        raise ConfigError(f"--set {item}: {name} is {chosen_elsewhere(cls, field)}, not --set")
    hint = hints[field]
    args = typing.get_args(hint)
    if hint is bool:
        if text in _TRUE:
            return True
        if text in _FALSE:
            return False
        raise ConfigError(f"--set {item}: {name} must be true or false, got {text!r}")
    if type(None) in args and text in ("None", "null"):
        return None
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = text
    numeric = {int, float} & ({hint} | set(args))
    if numeric and (isinstance(value, bool) or text in ("True", "False")):
        kind = "an int" if numeric == {int} else "a number"
        raise ConfigError(f"--set {item}: {name} must be {kind}, not a boolean")
    return tuple(value) if isinstance(value, list) else value


def parse_override(item: str, sections: Mapping[str, type]) -> tuple[str, str, Any]:
    """One `--set SECTION.FIELD=VALUE` item -> (section, field, value), the value read by the
    field's type (`field_value`); `sections` as `override_sections` gives them ('' for fields
    without a section: `--set FIELD=VALUE`). ConfigError naming the item."""
    key, sep, text = item.partition("=")
    if not sep:
        form = "SECTION.FIELD=VALUE" if set(sections) - {""} else "FIELD=VALUE"
        raise ConfigError(f"--set {item!r}: expected {form}")
    section, _, field = key.rpartition(".")
    if section not in sections:
        names = [s for s in sections if s] + (["a top-level field"] if "" in sections else [])
        use = " or ".join(filter(None, (", ".join(names[:-1]), names[-1])))
        raise ConfigError(f"--set {item!r}: unknown section {section!r}; use {use}")
    return section, field, field_value(item, sections[section], field, text)


def apply_overrides(
    cfg: C, items: Iterable[str] = (), changes: Mapping[str, Any] | None = None
) -> C:
    """`cfg` (a run-config dataclass) with `changes` ('section.field' or a top-level 'field' ->
    typed value, e.g. {'train.eps': 0.0, 'seed': 3}) and then the `--set` `items`
    ('SECTION.FIELD=VALUE' strings, `parse_override`) applied; a later one wins. Each section is
    rebuilt, so a wrong value is its ConfigError naming the field."""
    sections = override_sections(type(cfg))
    triples = []
    for key, value in (changes or {}).items():
        section, _, field = key.rpartition(".")
        cls = sections.get(section)
        if cls is None or field not in {f.name for f in dataclasses.fields(cls)}:
            owner = cls.__name__ if cls else f"section {section!r} of {type(cfg).__name__}"
            note = _removed_note(cls, [field]) if cls else ""
            raise ConfigError(f"{owner} has no field(s) {[field]}{note}")
        triples.append((section, field, value))
    triples += [parse_override(item, sections) for item in items]
    grouped: dict[str, dict[str, Any]] = {}
    for section, field, value in triples:
        grouped.setdefault(section, {})[field] = value
    top = grouped.pop("", {})
    env = grouped.pop("env", None)
    new = {s: dataclasses.replace(getattr(cfg, s), **fields) for s, fields in grouped.items()}
    if env is not None:
        new["env_overrides"] = {**cfg.env_overrides, **env}  # type: ignore[attr-defined]
    return dataclasses.replace(cfg, **{**top, **new})  # type: ignore[type-var]


def task_source(
    env: str,
    scenarios: str | os.PathLike | None = None,
    hold_out_val: bool = False,
    data: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """The top-level config fields of a run's task source: `task_options` for the paper's
    scenarios in the folder `scenarios` (restaurant; its files are checked now and their sha256
    recorded; `hold_out_val` keeps tasks 150-179 out of training), `data` for a trajectory file
    (sidewalk; checked to exist). {} for the family's generated tasks. ConfigError in one line."""
    out: dict[str, Any] = {}
    if hold_out_val and scenarios is None:
        raise ConfigError("--hold-out-val applies to --scenarios")
    if scenarios is not None:
        if env != "restaurant":
            raise ConfigError("--scenarios: the paper's scenarios are restaurant tasks")
        from mpcpearl_jax.envs.restaurant import scenario_options

        try:
            out["task_options"] = scenario_options(scenarios, hold_out_val)
        except OSError as e:
            raise ConfigError(str(e)) from e
    if data is not None:
        if Path(data).is_dir():
            raise ConfigError(
                f"--data {data}: a folder; give a trajectory file in it (ETH/UCY, e.g. "
                "crowds_zara01.txt)"
            )
        if not Path(data).is_file():
            raise ConfigError(f"--data {data}: no such file")
        out["data"] = str(data)
    return out


def read_config(path: str | os.PathLike) -> ExperimentConfig:
    """A run's recorded config (RUN/config.json, or the run folder) as the base of a new run,
    through `ExperimentConfig.from_dict`. A run that switched on a removed option
    (`removed_options_on`) cannot be repeated: ConfigError naming the options; a file that is
    not an MPC-PEARL run's config is a ConfigError naming it too."""
    path = Path(path)
    if path.is_dir():
        path = path / "config.json"
    try:
        raw = json.loads(path.read_text())
    except OSError as e:
        raise ConfigError(f"--config {path}: {e.strerror or type(e).__name__}") from e
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"--config {path}: not a JSON config ({e})") from e
    if not isinstance(raw, dict) or "method" in raw:
        what = f"a {raw['method']} run's config" if isinstance(raw, dict) else "not a dict"
        raise ConfigError(f"--config {path}: {what}, not an MPC-PEARL run's")
    on = removed_options_on(raw)
    if on:
        raise ConfigError(
            f"--config {path}: the run switched on {', '.join(on)}, option(s) since removed "
            "(docs/extensions.md, Removed options); it cannot be trained again"
        )
    try:
        return ExperimentConfig.from_dict(raw)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"--config {path}: {e}") from e


def resolve(
    base: str | C = "default",
    env: str | None = None,
    *,
    config_type: type | None = None,
    changes: Mapping[str, Any] | None = None,
    overrides: Iterable[str] = (),
    scenarios: str | os.PathLike | None = None,
    hold_out_val: bool = False,
    data: str | os.PathLike | None = None,
) -> Any:
    """The config of a run on task family `env`, of every algorithm (its run-config class:
    `config_type`, `ExperimentConfig` by default; GrBAL's is `GrbalExperimentConfig`, each
    registered algorithm's `mpcpearl_jax.algorithms.Algorithm.config_type`).

    `base` is a preset name of `config_type` or a config. A preset gets the family's settings
    (`config_type.from_preset`; MPC-PEARL's: the `default` preset re-draws crowds only where the
    family can, `envs.can_redraw`, and never on the paper's scenarios, the family's MPC defaults
    `envs.mpc_defaults` and its headline protocol `envs.online_eval`). A config (a run's
    config.json, `read_config`) is taken as recorded; `env`, if given, must be its family.
    Then, in this order (a later one wins): the task source (`task_source`: `scenarios`,
    `hold_out_val`, `data`), the typed `changes` and the `--set` `overrides`
    (`apply_overrides`). Last, the checks across fields (`validated`; MPC-PEARL's: `validate`):
    the result is a config a run can start from. ConfigError naming the field.
    """
    if isinstance(base, str):
        kind: Any = config_type or ExperimentConfig
        cfg: Any = kind.from_preset(base, env, scenarios=scenarios)
    else:
        cfg = base
        if env is not None and env != cfg.env:
            raise ConfigError(
                f"{type(cfg).__name__}.env: the config is of {cfg.env!r}, not {env!r}"
            )
    cfg = cfg.replace(**task_source(cfg.env, scenarios, hold_out_val, data))
    return apply_overrides(cfg, overrides, changes).validated()
