"""Navigation environments: `make_env(name)` and `make_tasks(name, split, seed=0)`.

Task families register a config, a task builder and optionally a redraw function and a figure
viewer here (each family's package registers itself on import: `restaurant`, `sidewalk`); see
`register` to add your own.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.numpy_ref import NumpyNavEnv, task_to_numpy
from mpcpearl_jax.envs.types import EnvState, NavConfig, StepInfo, TaskParams
from mpcpearl_jax.errors import ConfigError

SPLITS = ("train", "test", "ood", "val")

# name -> (default config, task builder(split, seed, config, **kwargs) -> stacked TaskParams)
_REGISTRY: dict[str, tuple[NavConfig, Callable[..., TaskParams]]] = {}
# name -> redraw(seed, config, task_ids, stream, **kwargs) -> stacked TaskParams (optional)
_REDRAW: dict[str, Callable[..., TaskParams]] = {}
# name -> viewer(path, task, robots, config, title=None) -> Path (optional; see save_trajectory)
_VIEWER: dict[str, Callable[..., Path]] = {}
# name -> MPCConfig field defaults of the family (optional; see mpc_defaults)
_MPC_DEFAULTS: dict[str, dict[str, Any]] = {}
# families whose headline evaluation is online adaptation (see online_eval)
_ONLINE: set[str] = set()
# the validation set of a family without a 'val' split: its first VAL_TASKS training tasks
VAL_TASKS = 24


def register(
    name: str,
    config: NavConfig,
    builder: Callable[..., TaskParams],
    redraw: Callable[..., TaskParams] | None = None,
    viewer: Callable[..., Path] | None = None,
    mpc_defaults: dict[str, Any] | None = None,
    online_eval: bool = False,
) -> None:
    """Register a task family so that `make_env(name)` and `make_tasks(name, ...)` know it.

    `redraw(seed, config, task_ids, stream, **kwargs)`, optional, returns the training tasks
    `task_ids` with their people's behaviour drawn anew from the random stream `stream` (a tuple
    of ints); it backs the `TrainConfig.redraw_behaviours` extension.
    `viewer(path, task, robots, config, title=None)`, optional, saves the family's trajectory
    figure (see `save_trajectory`); default: `envs.drawing.save_robots_figure`.
    `mpc_defaults`, optional: MPCConfig fields this family sets unless a run overrides them
    (see `mpc_defaults`). `online_eval`: online adaptation is the family's headline evaluation
    (see `online_eval`)."""
    _REGISTRY[name] = (config, builder)
    _MPC_DEFAULTS[name] = dict(mpc_defaults or {})
    if online_eval:
        _ONLINE.add(name)
    else:
        _ONLINE.discard(name)
    for table, fn in ((_REDRAW, redraw), (_VIEWER, viewer)):
        if fn is not None:
            table[name] = fn
        else:
            table.pop(name, None)


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


def load_family(spec: str) -> str:
    """The name of the task family `spec` names: NAME, a registered family (`restaurant`,
    `sidewalk`), or MODULE:NAME, whose MODULE is imported first (importing it registers NAME;
    e.g. `examples.corridor:corridor`, docs/custom_tasks.md). ValueError, starting with `spec`,
    when the module or the family is missing, or when importing the module fails (its error, a
    syntax error or an exit, in one line)."""
    import importlib

    module, sep, name = spec.partition(":")
    if not sep:
        if spec not in _REGISTRY:
            raise ValueError(f"{spec}: no such task family; known: {env_names()} or MODULE:NAME")
        return spec
    if not module or not name:
        raise ValueError(f"{spec}: expected MODULE:NAME, e.g. examples.corridor:corridor")
    try:
        importlib.import_module(module)
    except ModuleNotFoundError as e:
        raise ValueError(
            f"{spec}: no module named {e.name!r} (run from the folder that holds {module!r}, or "
            f"install its package)"
        ) from None
    except SyntaxError as e:
        raise ValueError(
            f"{spec}: {module} has a syntax error ({e.msg}, {e.filename} line {e.lineno})"
        ) from None
    except SystemExit as e:  # an exit while importing: nothing was registered or printed
        raise ValueError(f"{spec}: importing {module} exited (sys.exit({e.code!r}))") from None
    except Exception as e:  # noqa: BLE001 - the module's own error, as one line
        first = (str(e).strip().splitlines() or [""])[0]
        raise ValueError(
            f"{spec}: importing {module} failed: {type(e).__name__}"
            + (f": {first}" if first else "")
        ) from None
    if name not in _REGISTRY:
        raise ValueError(
            f"{spec}: importing {module} registered no family {name!r}; known: {env_names()}"
        )
    return name


def make_env(name: str, /, **overrides: Any) -> NavEnv:
    """The environment of a task family; keyword overrides replace `NavConfig` fields."""
    config, _ = _lookup(name)
    if "name" in overrides:  # it would be a second value for `name`
        raise ConfigError(
            "NavConfig.name is the task family (make_env's name, --env), not an override"
        )
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


def mpc_defaults(name: str) -> dict[str, Any]:
    """The MPCConfig field defaults of family `name` (a copy), applied under a run's own MPC
    settings by every command line (e.g. the sidewalk's speed cap: the env's v_max)."""
    _lookup(name)
    return dict(_MPC_DEFAULTS.get(name, {}))


def online_eval(name: str) -> bool:
    """Whether online adaptation is the headline evaluation of family `name` (a run's
    `online_eval` unless it overrides it; the sidewalk, as in the paper)."""
    _lookup(name)
    return name in _ONLINE


def tasks_for(
    cfg: Any, split: str, *, config: NavConfig | None = None, seed: int | None = None
) -> TaskParams:
    """The tasks of `split` for a run config (`ExperimentConfig`, `GrbalExperimentConfig`: its
    `env`, `task_seed`, `data` file and `task_options`), stacked on a leading axis. `config`: the
    NavConfig the tasks are built for (default: the family's with the run's `env_overrides`);
    `seed`: a task-set seed other than the run's."""
    kw: dict[str, Any] = {"data": cfg.data} if cfg.data else {}
    kw.update(cfg.task_options)
    if config is None:
        config = make_env(cfg.env, **cfg.env_overrides).config
    return make_tasks(cfg.env, split, cfg.task_seed if seed is None else seed, config=config, **kw)


def validation_tasks(
    cfg: Any, *, config: NavConfig | None = None, train_tasks: TaskParams | None = None
) -> tuple[TaskParams, str]:
    """The validation set of a run config, on which settings are chosen (never the test set),
    and a line saying what it is: the family's 'val' split (the restaurant's held-out
    behaviours; with the paper's scenarios, tasks 150-179 when the run held them out of
    training); else the first `VAL_TASKS` training tasks (`train_tasks` when given, or all if
    fewer): the sidewalk, and a run that trained on every scenario."""
    import jax

    from mpcpearl_jax.envs.restaurant.scenarios import VAL_IDS, check_val_split, uses_scenarios

    try:
        check_val_split(cfg.task_options, "val")  # not the scenarios the run trains on
        tasks = tasks_for(cfg, "val", config=config)
    except ValueError:
        train = tasks_for(cfg, "train", config=config) if train_tasks is None else train_tasks
        tasks = jax.tree_util.tree_map(lambda x: x[:VAL_TASKS], train)
        return tasks, f"the first {VAL_TASKS} training tasks (or all if fewer)"
    if uses_scenarios(cfg.task_options):
        return tasks, f"the paper's scenarios {VAL_IDS[0]}-{VAL_IDS[-1]} (held out of training)"
    return tasks, "the family's 'val' split (held-out behaviours, neither train nor test)"


def save_trajectory(
    name: str,
    path: str | Path,
    task: TaskParams,
    robots: Mapping[str, tuple[Any, Any]],
    config: NavConfig | None = None,
    title: str | None = None,
) -> Path:
    """Save the trajectory figure of one task of family `name` in the family's style (its
    registered viewer, or the shared default). robots: label -> (positions [T + 1, 2],
    collisions [T] bool or None). Returns the path."""
    default, _ = _lookup(name)
    viewer = _VIEWER.get(name)
    if viewer is None:
        from mpcpearl_jax.envs.drawing import save_robots_figure as viewer
    return viewer(Path(path), task, robots, config or default, title)


def _register_builtin() -> None:
    """The built-in families register themselves on import (an import error is an error)."""
    from mpcpearl_jax.envs import restaurant, sidewalk  # noqa: F401


_register_builtin()

# brax and gymnasium are imported only when an adapter is used
_LAZY = {
    "BraxNavEnv": "brax_adapter",
    "GymNavEnv": "gymnasium_adapter",
    "GymNavVectorEnv": "gymnasium_adapter",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "SPLITS",
    "VAL_TASKS",
    "BraxNavEnv",
    "ConfigError",
    "EnvState",
    "GymNavEnv",
    "GymNavVectorEnv",
    "NavConfig",
    "NavEnv",
    "NumpyNavEnv",
    "StepInfo",
    "TaskParams",
    "can_redraw",
    "env_names",
    "load_family",
    "make_env",
    "make_tasks",
    "mpc_defaults",
    "online_eval",
    "redraw_tasks",
    "register",
    "save_trajectory",
    "task_to_numpy",
    "tasks_for",
    "validation_tasks",
]
