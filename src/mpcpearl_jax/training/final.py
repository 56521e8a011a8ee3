"""The end of a training, and the one entry to it, for Python and the training commands alike.

`train(cfg, out, minutes=None, options=TrainOptions(...))` checks its arguments, opens the run
folder (new, resumed or overwritten), trains by the run's kind (MPC-PEARL: the iterations mode,
`run.train_iterations`, or the minutes mode, `budget.train_minutes`; GrBAL: `grbal.run`'s rules)
and `finish`es: the learning curve (a minutes run: curve.json, curve.png), then the final
evaluation of the trained policy, `final_evaluation`: the test tasks (adaptation and online)
and the OOD tasks of the run's own task source, written into its folder as results.json, the
learning curves, trajectory figures and an animated episode. Nothing here prints: a caller sees
the run through `TrainOptions`' callbacks and the return value (the training commands,
`mpcpearl_jax.cli.train`, print the progress, the results table and their lines).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.distributed import is_primary
from mpcpearl_jax.evaluation.report import PAPER, plot_learning_curves, run_label
from mpcpearl_jax.grbal.run import GRBAL
from mpcpearl_jax.grbal.run import LABEL as GRBAL_LABEL
from mpcpearl_jax.grbal.run import final_evaluation as grbal_final_evaluation
from mpcpearl_jax.grbal.run import train_iterations as grbal_iterations
from mpcpearl_jax.runfolder import LOG_FILE, read_log, write_json
from mpcpearl_jax.training.budget import (
    CURVE_FILE,
    load_at_start,
    train_minutes,
    warn_if_busy,
    write_curve,
)
from mpcpearl_jax.training.machine import machine_info
from mpcpearl_jax.training.run import (
    PEARL,
    RunInterrupted,
    RunKind,
    Session,
    open_session,
    train_iterations,
)
from mpcpearl_jax.training.trainer import Trainer, TrainState


@dataclasses.dataclass(frozen=True)
class TrainOptions:
    """What a caller of `train` chooses beside the config, the folder and the budget.

    resume: continue the run in `out` (its config, checkpoints and log); overwrite: replace the
    run in `out` (not both). A time budget's options: `eval_minutes` (minutes of training
    between the curve's evaluations, default minutes / 8), `policy_only` (policy.msgpack alone,
    no checkpoint to resume from), `record` (fields curve.json records, e.g. the command line's
    preset and argv) and `clock` (what times the budget; tests give a fake one). `tensorboard`:
    every metrics row also to <out>/tensorboard.

    The callbacks, each optional, are how a caller sees a run as it goes (nothing here prints):
    `on_start(session)` once the run folder is open, before the first iteration;
    `on_row(row)` after every iteration (its metrics row, with the evaluation's fields when it
    evaluated); `on_point(point)` at each eval point of a time budget; `on_trained(info)` once
    training stops, however it stops, before the final evaluation (info: the mode's record:
    "stopped", "iterations", "train_s", ...; a time budget's eval "points" too)."""

    resume: bool = False
    overwrite: bool = False
    eval_minutes: float | None = None
    policy_only: bool = False
    tensorboard: bool = False
    record: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    clock: Callable[[], float] = time.perf_counter
    on_start: Callable[[Session], None] | None = None
    on_row: Callable[[dict[str, Any]], None] | None = None
    on_point: Callable[[dict[str, Any]], None] | None = None
    on_trained: Callable[[dict[str, Any]], None] | None = None

    def __post_init__(self) -> None:
        """Each option's type checked at construction: TypeError naming the option."""

        def wrong(name: str, expected: str) -> TypeError:
            x = getattr(self, name)
            return TypeError(
                f"TrainOptions: {name} must be {expected}, not {type(x).__name__} {x!r}"
            )

        for name in ("resume", "overwrite", "policy_only", "tensorboard"):
            if not isinstance(getattr(self, name), bool):
                raise wrong(name, "True or False")
        m = self.eval_minutes
        if m is not None and (isinstance(m, bool) or not isinstance(m, (int, float))):
            raise wrong("eval_minutes", "a number of minutes (or None: minutes / 8)")
        if not isinstance(self.record, Mapping):
            raise wrong("record", "a mapping of the fields curve.json records")
        if not callable(self.clock):
            raise wrong("clock", "a function returning seconds")
        for name in ("on_start", "on_row", "on_point", "on_trained"):
            if getattr(self, name) is not None and not callable(getattr(self, name)):
                raise wrong(name, "a function (or None)")


def train(
    cfg: Any,
    out: str | os.PathLike,
    minutes: float | None = None,
    *,
    label: str | None = None,
    options: TrainOptions | None = None,
) -> tuple[Any, dict[str, Any]]:
    """Train `cfg` (a config from `config.resolve`, or a GrBAL one from `grbal.config.resolve`)
    into the run folder `out`: its iterations, or `minutes` minutes of training (MPC-PEARL: with a
    learning curve, `budget.train_minutes`; GrBAL: its iterations, stopped early when the time is
    up); then `finish`: the final evaluation (results.json, figures). `options`
    (`TrainOptions`): resume, overwrite, the callbacks. Returns (state, results): the trained
    state and results.json's content. `label` names the run in its results and figures
    (default: the method's, e.g. "MPC-PEARL 0.2").

    Every argument is checked before anything is created (TypeError or ValueError, one sentence
    naming what it expects). A diverged training raises TrainingDiverged (a time budget's curve
    written first); a stop signal (Ctrl-C, SIGTERM, SIGHUP) stops at the next phase boundary and
    raises RunInterrupted, the last finished iteration saved (a second one: KeyboardInterrupt at
    once)."""
    kind = check_train_arguments(cfg, out, minutes, label, options)
    opts = options or TrainOptions()
    curve = kind is PEARL and minutes is not None
    label = label or (run_label(cfg) if kind is PEARL else GRBAL_LABEL)
    load_start = load_at_start() if curve else None
    t_wall0 = time.perf_counter()
    with open_session(
        cfg,
        Path(out),
        opts.resume,
        until_budget=curve,
        kind=kind,
        tensorboard=opts.tensorboard,
        overwrite=opts.overwrite,
    ) as sess:
        if curve:
            warn_if_busy(load_start)  # measured before the trainer was built
        build_s = time.perf_counter() - t_wall0  # the trainer and its initial or restored state
        if opts.on_start is not None:
            opts.on_start(sess)
        if kind is GRBAL:
            state, info = _grbal_rules(sess, minutes, opts)
        elif minutes is None:
            state, info = train_iterations(sess, opts.on_row, handle_sigint=True)
        else:
            state, info = train_minutes(
                sess,
                minutes=minutes,
                eval_minutes=opts.eval_minutes,
                policy_only=opts.policy_only,
                on_point=opts.on_point,
                on_row=opts.on_row,
                clock=opts.clock,
            )
        if opts.on_trained is not None:
            opts.on_trained(info)
        extra: dict[str, Any] = {}
        if curve:
            extra = dict(opts.record, resumed=opts.resume, load_start=load_start)
            extra.update(build_s=build_s, t_wall0=t_wall0)
        results = finish(sess, state, info, label=label, **extra)
        if "error" in info:  # interrupted or diverged: what could be written is written
            raise info["error"]
        return state, results or {}


def check_train_arguments(
    cfg: Any, out: Any, minutes: Any, label: Any = None, options: Any = None
) -> RunKind:
    """`train`'s arguments checked before anything is created: -> the run's kind (PEARL or
    GRBAL, from the config's type); TypeError or ValueError, one sentence naming what is
    expected, otherwise."""
    from mpcpearl_jax.grbal.config import GrbalExperimentConfig

    if isinstance(cfg, ExperimentConfig):
        kind: RunKind = PEARL
    elif isinstance(cfg, GrbalExperimentConfig):
        kind = GRBAL
    else:
        hint = (
            f" (for a preset: mpcpearl_jax.config.resolve({cfg!r}))" if isinstance(cfg, str) else ""
        )
        raise TypeError(
            "mpcpearl_jax.train: cfg must be a run config (mpcpearl_jax.config.resolve(preset, "
            f"env), or a GrBAL one from grbal.config.resolve), not {type(cfg).__name__}{hint}"
        )
    if not isinstance(out, (str, os.PathLike)) or not str(out):
        raise TypeError(
            f"mpcpearl_jax.train: out must be a folder path (a str or a Path), not {out!r}"
        )
    if minutes is not None:
        if isinstance(minutes, bool) or not isinstance(minutes, (int, float)):
            raise TypeError(
                "mpcpearl_jax.train: minutes must be a number of minutes of training (or None: "
                f"the config's iterations), not {type(minutes).__name__} {minutes!r}"
            )
        if not (minutes > 0 and math.isfinite(minutes)):
            raise ValueError(
                f"mpcpearl_jax.train: minutes must be positive and finite, got {minutes}"
            )
    if label is not None and not isinstance(label, str):
        raise TypeError(f"mpcpearl_jax.train: label must be a str, not {type(label).__name__}")
    if options is not None and not isinstance(options, TrainOptions):
        raise TypeError(
            "mpcpearl_jax.train: options must be a mpcpearl_jax.training.final.TrainOptions, "
            f"not {type(options).__name__}"
        )
    opts = options or TrainOptions()
    if opts.resume and opts.overwrite:
        raise ValueError("mpcpearl_jax.train: resume or overwrite, not both")
    budget_only = (
        ("eval_minutes", opts.eval_minutes is not None),
        ("policy_only", opts.policy_only),
    )
    for name, given in budget_only:
        if given and (minutes is None or kind is not PEARL):
            raise ValueError(f"mpcpearl_jax.train: {name} applies to an MPC-PEARL time budget")
    if opts.eval_minutes is not None and not opts.eval_minutes > 0:
        raise ValueError(
            f"mpcpearl_jax.train: eval_minutes must be positive, got {opts.eval_minutes}"
        )
    if opts.resume and opts.policy_only:
        raise ValueError(
            "mpcpearl_jax.train: resume continues from a checkpoint: not with policy_only"
        )
    return kind


def _grbal_rules(
    sess: Session, minutes: float | None, opts: TrainOptions
) -> tuple[Any, dict[str, Any]]:
    """GrBAL's rules (`grbal.run.train_iterations`); -> (state, info) with info["error"] the
    exception of a stop or a divergence (then state is None), as the MPC-PEARL modes return."""
    from mpcpearl_jax.errors import TrainingDiverged

    try:
        return grbal_iterations(sess, opts.on_row, minutes, handle_sigint=True)
    except (RunInterrupted, TrainingDiverged) as e:
        p, stopped = (
            sess.progress,
            ("interrupted" if isinstance(e, RunInterrupted) else f"diverged: {e}"),
        )
        info = {"mode": "iterations", "stopped": stopped, "error": e, "lost": getattr(e, "lost", 0)}
        info.update(iterations=getattr(e, "iteration", p.iterations), saved=p.saved)
        info.update(train_s=p.train_s, first_iteration_s=p.first_iteration_s)
        return None, info


def finish(
    sess: Session,
    state: Any,
    info: dict[str, Any],
    *,
    label: str,
    t_wall0: float | None = None,
    **curve: Any,
) -> dict[str, Any] | None:
    """What a training writes once it stops (`info`: the mode's): a minutes run's learning curve
    (`budget.write_curve`, with `curve`'s fields recorded), then, once training is done (not
    interrupted, diverged or without an iteration), the final evaluation (`final_evaluation`);
    the curve records how long that took and, from `t_wall0` (`time.perf_counter()` before the
    session was opened), the whole run. Returns results.json's content, or None where not
    evaluated; info["curve"] is the curve's record (minutes mode)."""
    record = None
    if info["mode"] == "minutes":
        record = info["curve"] = write_curve(sess, info, label=label, **curve)
    if info["stopped"] == "interrupted" or not info["iterations"]:
        return None
    t, results = time.perf_counter(), None
    if info["stopped"] in ("done", "budget") and sess.kind is GRBAL:
        results = grbal_final_evaluation(sess.trainer, state, sess.run_dir)
    elif info["stopped"] in ("done", "budget"):
        results = final_evaluation(sess.trainer, state, sess.run_dir, label)
    if record is not None:
        record["timing"]["final_evaluation_s"] = time.perf_counter() - t
        if t_wall0 is not None:
            record["timing"]["total_wall_s"] = time.perf_counter() - t_wall0
        write_json(sess.run_dir / CURVE_FILE, record)
    return results


def final_evaluation(
    trainer: Trainer, state: TrainState, out: str | Path, label: str
) -> dict[str, Any]:
    """Evaluate on test (adaptation and online) and OOD tasks; save results.json + figures."""
    from mpcpearl_jax.envs import tasks_for

    run_dir = Path(out)
    results: dict[str, Any] = {
        "label": label,
        "env": trainer.cfg.env,
        "config": trainer.cfg.to_dict(),
    }
    adapt, raw = trainer.evaluate_episodes(state)
    results["test_adapt"] = adapt
    results["test_online"] = trainer.evaluate(state, online=True)
    try:  # the OOD split of the run's own task source (its task options: e.g. the scenarios)
        ood = tasks_for(trainer.cfg, "ood", config=trainer.env.config)
        results["ood_adapt"] = trainer.evaluate(state, tasks=ood)
    except (ValueError, FileNotFoundError) as e:  # no OOD split (or no OOD scenario file)
        results["ood_adapt"] = {"skipped": str(e)}
    results["paper"] = PAPER.get(trainer.cfg.env, {})
    results["machine"] = machine_info()  # run times depend on it (CPU model, cores, versions)
    if not is_primary():  # every process evaluates its seeds; process 0 writes
        return results
    rows = read_log(run_dir / LOG_FILE)  # the saved policy is the last iteration's: marked
    plot_learning_curves([(label, rows)], run_dir / "learning_curves.png", saved_last=True)
    _trajectory_figure(trainer, raw, run_dir)
    _episode_gif(trainer, raw, run_dir, label)
    # last: results.json marks the run finished (--resume then has nothing to do), so a stop
    # before it (in the figures) leaves the final evaluation for --resume to run again
    write_json(run_dir / "results.json", results)
    return results


def _episode_gif(trainer: Trainer, raw: dict, run_dir: Path, label: str) -> Path:
    """episode_test0.gif: seed 0's evaluated episode on test task 0
    (`mpcpearl_jax.evaluation.animate`)."""
    from mpcpearl_jax.evaluation.animate import animate_result

    title = f"{label} (seed 0), {trainer.cfg.env} test task 0"
    path = run_dir / "episode_test0.gif"
    return animate_result(path, raw, trainer.test_tasks, trainer.env.config, title=title)


def _trajectory_figure(trainer: Trainer, raw: dict, run_dir: Path, n: int = 4) -> None:
    """The first n test tasks with seed 0's evaluated episode (paper-style figures, in the
    family's style: its registered viewer)."""
    from mpcpearl_jax.envs import save_trajectory

    for i in range(min(n, int(trainer.test_tasks.start.shape[0]))):
        task = jax.tree_util.tree_map(lambda x, i=i: x[i], trainer.test_tasks)
        pos = np.asarray(raw["position"][0, i])
        col = np.asarray(raw["collision"][0, i])
        path = run_dir / f"trajectory_test{i}.png"
        robots = {"policy (seed 0)": (pos, col)}
        save_trajectory(trainer.cfg.env, path, task, robots, trainer.env.config)
