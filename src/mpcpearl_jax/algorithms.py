"""The algorithms a run trains, one registered object each (as task families register in
`mpcpearl_jax.envs`; in acme's words, a builder per agent): `Algorithm` carries its run-config
type and presets, its trainer factory (the run session's `RunKind`), its training rules, its
final evaluation, its label, its progress line, its evaluation setup and what its training
command shows of it (its command, families, run folder, first line, preset notes).
`mpcpearl_jax.train` (`api.train`), the training commands (`cli.args`, `cli.train`) and the
evaluation (`api.evaluate`) dispatch on it; nothing above this module asks which algorithm a run
is.

Registered here: "mpc-pearl" (MPC-PEARL and its baselines, which are configs of it: PEARL with
eps 0, MPC-SAC without the encoder) and "grbal" (the GrBAL baseline, `mpcpearl_jax.grbal`).
`register` adds another; `of_config(cfg)` and `of_run(run_dir)` find a config's or a run
folder's.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from mpcpearl_jax.config import PRESETS, ExperimentConfig
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.evaluation.report import run_label
from mpcpearl_jax.grbal import run as grbal_run
from mpcpearl_jax.grbal.config import PRESETS as GRBAL_PRESETS
from mpcpearl_jax.grbal.config import GrbalExperimentConfig
from mpcpearl_jax.grbal.evaluation import evaluation_setup as grbal_evaluation_setup
from mpcpearl_jax.runfolder import CONFIG_FILE
from mpcpearl_jax.training import final
from mpcpearl_jax.training.budget import train_minutes
from mpcpearl_jax.training.options import TrainOptions
from mpcpearl_jax.training.run import PEARL, RunInterrupted, RunKind, Session, train_iterations

# rules(session, minutes, options) -> (state, info): the mode's record, info["error"] the
# exception of a stop or a divergence (then written up to it, raised by `train` after `finish`)
Rules = Callable[[Session, "float | None", TrainOptions], "tuple[Any, dict[str, Any]]"]


@dataclasses.dataclass(frozen=True)
class Algorithm:
    """One algorithm a run trains.

    name: how commands and run folders name it (config.json's `method`, absent for
    "mpc-pearl"); config_type: its run-config class (`config.resolve(..., config_type=...)`
    builds one from a preset of `presets`); kind: the run session's `RunKind` (its trainer
    factory, what policy.msgpack holds, its config section); rules: how it trains on an open
    session (`Rules`); final_evaluation(trainer, state, run_dir, label) -> results.json's
    content (written with its figures); label(cfg): the name of its runs in results and
    figures; learning_curve: whether a time budget (`minutes`) trains with a learning curve
    (curve.json; the budget's options `eval_minutes`, `policy_only` apply), otherwise minutes
    only stop the iterations early; progress_line(row, cfg): its line per iteration (None: the
    training command's progress bar); evaluation_setup(run_dir, **arguments) -> the evaluation's
    (`evaluation.runners.Setup`, the number of tasks) of a run folder of this algorithm evaluated
    as trained (None: the policy evaluation of `api.evaluate`).

    What its training command shows of it: command, the module of its own command (`python -m
    experiments.COMMAND`: --env picks one of `families`, --preset one of `presets`, --minutes
    stops the iterations early; a stop outside training names the command that goes on by
    whether the run's config.json is written), None where the task families' commands train it
    (restaurant, sidewalk, learning: their options, progress bar and closing lines);
    iterations_help, its --iterations' help; run_folder, the default run folder under runs/ as a
    format of {env} and {preset} (None: the run's label); summary(cfg), what the command's first
    line adds about the config; notes, a line per preset printed when that preset trains as it
    is (no --config, no --iterations)."""

    name: str
    config_type: type
    presets: Mapping[str, Any]
    kind: RunKind
    rules: Rules
    final_evaluation: Callable[[Any, Any, Path, str], dict[str, Any]]
    label: Callable[[Any], str]
    learning_curve: bool = False
    progress_line: Callable[[dict[str, Any], Any], str] | None = None
    evaluation_setup: Callable[..., Any] | None = None
    command: str | None = None
    families: tuple[str, ...] = ()
    iterations_help: str = "training iterations"
    run_folder: str | None = None
    summary: Callable[[Any], str] | None = None
    notes: Mapping[str, str] = dataclasses.field(default_factory=dict)

    @property
    def iterations_field(self) -> str:
        """The config field that holds the run's iterations ('train.iterations')."""
        return f"{self.kind.section}.iterations"

    def iterations(self, cfg: Any) -> int:
        """The iterations a config of this algorithm trains."""
        return getattr(cfg, self.kind.section).iterations


_REGISTRY: dict[str, Algorithm] = {}
DEFAULT = "mpc-pearl"


def register(algorithm: Algorithm) -> Algorithm:
    """Register `algorithm` under its name (a later one replaces it); -> it."""
    if not isinstance(algorithm, Algorithm):
        raise TypeError(f"register: an Algorithm, not {type(algorithm).__name__}")
    _REGISTRY[algorithm.name] = algorithm
    return algorithm


def names() -> list[str]:
    return sorted(_REGISTRY)


def get(name: str) -> Algorithm:
    """The algorithm registered as `name`; ConfigError naming the registered ones otherwise."""
    if name not in _REGISTRY:
        raise ConfigError(f"unknown algorithm {name!r}; registered: {names()}")
    return _REGISTRY[name]


def of_config(cfg: Any) -> Algorithm | None:
    """The algorithm whose run-config type `cfg` is (None: no registered one's)."""
    return next((a for a in _REGISTRY.values() if isinstance(cfg, a.config_type)), None)


def of_run(run_dir: str | Path) -> Algorithm:
    """The algorithm that made the run in `run_dir` (its config.json's `method`; MPC-PEARL
    where there is none, or no readable config: opening the run names the problem)."""
    try:
        raw = json.loads((Path(run_dir) / CONFIG_FILE).read_text())
        method = raw.get("method") if isinstance(raw, dict) else None
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        method = None
    return _REGISTRY.get(method or DEFAULT, _REGISTRY[DEFAULT])


# ---------------------------------------------------------------------------------- MPC-PEARL
def _pearl_rules(
    sess: Session, minutes: float | None, opts: TrainOptions
) -> tuple[Any, dict[str, Any]]:
    """The iterations mode (`run.train_iterations`), or a time budget with its learning curve
    (`budget.train_minutes`)."""
    if minutes is None:
        return train_iterations(sess, opts.on_row, handle_sigint=True)
    return train_minutes(
        sess,
        minutes=minutes,
        eval_minutes=opts.eval_minutes,
        policy_only=opts.policy_only,
        on_point=opts.on_point,
        on_row=opts.on_row,
        clock=opts.clock,
    )


def _pearl_final(trainer: Any, state: Any, run_dir: Path, label: str) -> dict[str, Any]:
    return final.final_evaluation(trainer, state, run_dir, label)  # looked up at each call


# the default preset's expectations, printed on the first lines of its training
_PEARL_DEFAULT_NOTE = (
    "the default preset: a first look, 75 iterations, about 4-5 minutes of training on a quiet "
    "2-core CPU, up to about 8 on a slower or busy one (the README gives the range over ten "
    "seeds); the first iteration compiles, up to a minute of it. Far shorter than the paper's "
    "training (printed under the results table)"
)

MPC_PEARL = register(
    Algorithm(
        name="mpc-pearl",
        config_type=ExperimentConfig,
        presets=PRESETS,
        kind=PEARL,
        rules=_pearl_rules,
        final_evaluation=_pearl_final,
        label=run_label,
        learning_curve=True,
        iterations_help="meta-training iterations",
        notes={"default": _PEARL_DEFAULT_NOTE},
    )
)


# -------------------------------------------------------------------------------------- GrBAL
def _grbal_rules(
    sess: Session, minutes: float | None, opts: TrainOptions
) -> tuple[Any, dict[str, Any]]:
    """GrBAL's rules (`grbal.run.train_iterations`, `minutes` stopping them early); -> (state,
    info) with info["error"] the exception of a stop or a divergence (then state is None), as
    the MPC-PEARL modes return."""
    from mpcpearl_jax.errors import TrainingDiverged

    try:
        return grbal_run.train_iterations(sess, opts.on_row, minutes, handle_sigint=True)
    except (RunInterrupted, TrainingDiverged) as e:
        p, stopped = (
            sess.progress,
            ("interrupted" if isinstance(e, RunInterrupted) else f"diverged: {e}"),
        )
        info = {"mode": "iterations", "stopped": stopped, "error": e, "lost": getattr(e, "lost", 0)}
        info.update(iterations=getattr(e, "iteration", p.iterations), saved=p.saved)
        info.update(train_s=p.train_s, first_iteration_s=p.first_iteration_s)
        return None, info


def _grbal_final(trainer: Any, state: Any, run_dir: Path, label: str) -> dict[str, Any]:
    return grbal_run.final_evaluation(trainer, state, run_dir)  # labelled grbal.run.LABEL


def _grbal_line(row: dict[str, Any], cfg: Any) -> str:
    """GrBAL's line per iteration: its fit, collection and model losses, the test metrics at
    evaluations."""
    parts = [
        f"it {row['iteration']}/{cfg.grbal.iterations}",
        f"fit {row['update_s']:.1f}s",
        f"collect {row['collect_s']:.1f}s",
        f"loss pre {row['model_pre_loss']:.3f} post {row['model_post_loss']:.3f}",
        f"train ret {row['train_return']:.0f} SR {row['train_success']:.2f}",
    ]
    if "test_SR" in row:
        parts.append(
            f"| test SR {row['test_SR']:.2f} CFR {row['test_CFR']:.2f} "
            f"ret {row['test_return']:.0f} ({row['eval_s']:.0f}s)"
        )
    return "  ".join(parts)


def _grbal_summary(cfg: Any) -> str:
    """GrBAL's model and planner, on the training command's first line."""
    g = cfg.grbal
    return (
        f"model={'x'.join(map(str, g.hidden))} MPPI {g.num_samples}x{g.mppi_iterations} "
        f"horizon {g.plan_horizon}"
    )


GRBAL = register(
    Algorithm(
        name="grbal",
        config_type=GrbalExperimentConfig,
        presets=GRBAL_PRESETS,
        kind=grbal_run.GRBAL,
        rules=_grbal_rules,
        final_evaluation=_grbal_final,
        label=lambda cfg: grbal_run.LABEL,
        progress_line=_grbal_line,
        evaluation_setup=grbal_evaluation_setup,
        command="grbal",
        families=("restaurant", "sidewalk"),
        iterations_help="training iterations (fit + collection)",
        run_folder="{env}-{preset}-grbal",
        summary=_grbal_summary,
    )
)
