"""`mpcpearl_jax.train`: the one entry to a training, for Python and the training commands
alike.

`train(cfg, out, minutes=None, options=TrainOptions(...))` checks its arguments, opens the run
folder (new, resumed or overwritten), trains by the rules of the config's algorithm (the one
`mpcpearl_jax.algorithms` registers for its type: MPC-PEARL's iterations mode or time budget,
GrBAL's iterations) and `finish`es (`training.final`): the learning curve (an MPC-PEARL time
budget: curve.json, curve.png), then the algorithm's final evaluation (results.json, figures).
Nothing here prints: a caller sees the run through `TrainOptions`' callbacks and the return
value (the training commands, `mpcpearl_jax.cli.train`, print the progress, the results table
and their lines).
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

from mpcpearl_jax import algorithms
from mpcpearl_jax.algorithms import Algorithm
from mpcpearl_jax.training.budget import load_at_start, warn_if_busy
from mpcpearl_jax.training.final import finish
from mpcpearl_jax.training.options import TrainOptions
from mpcpearl_jax.training.run import open_session

__all__ = ["TrainOptions", "check_train_arguments", "train"]


def train(
    cfg: Any,
    out: str | os.PathLike,
    minutes: float | None = None,
    *,
    label: str | None = None,
    options: TrainOptions | None = None,
) -> tuple[Any, dict[str, Any]]:
    """Train `cfg` (a config from `config.resolve`, MPC-PEARL's or another registered algorithm's)
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
    algorithm = check_train_arguments(cfg, out, minutes, label, options)
    opts = options or TrainOptions()
    curve = algorithm.learning_curve and minutes is not None
    label = label or algorithm.label(cfg)
    load_start = load_at_start() if curve else None
    t_wall0 = time.perf_counter()
    with open_session(
        cfg,
        Path(out),
        opts.resume,
        until_budget=curve,
        kind=algorithm.kind,
        tensorboard=opts.tensorboard,
        overwrite=opts.overwrite,
    ) as sess:
        if curve:
            warn_if_busy(load_start)  # measured before the trainer was built
        build_s = time.perf_counter() - t_wall0  # the trainer and its initial or restored state
        if opts.on_start is not None:
            opts.on_start(sess)
        state, info = algorithm.rules(sess, minutes, opts)
        if opts.on_trained is not None:
            opts.on_trained(info)
        extra: dict[str, Any] = {}
        if curve:
            extra = dict(opts.record, resumed=opts.resume, load_start=load_start)
            extra.update(build_s=build_s, t_wall0=t_wall0)
        results = finish(
            sess, state, info, label=label, evaluate=algorithm.final_evaluation, **extra
        )
        if "error" in info:  # interrupted or diverged: what could be written is written
            raise info["error"]
        return state, results or {}


def check_train_arguments(
    cfg: Any, out: Any, minutes: Any, label: Any = None, options: Any = None
) -> Algorithm:
    """`train`'s arguments checked before anything is created: -> the config's algorithm (the
    registered one of its type, `algorithms.of_config`); TypeError or ValueError, one sentence
    naming what is expected, otherwise."""
    algorithm = algorithms.of_config(cfg)
    if algorithm is None:
        hint = (
            f" (for a preset: mpcpearl_jax.config.resolve({cfg!r}))" if isinstance(cfg, str) else ""
        )
        raise TypeError(
            "mpcpearl_jax.train: cfg must be a run config (mpcpearl_jax.config.resolve(preset, "
            "env), or another registered algorithm's: resolve(preset, env, config_type=...)), "
            f"not {type(cfg).__name__}{hint}"
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
            "mpcpearl_jax.train: options must be a mpcpearl_jax.training.options.TrainOptions, "
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
        if given and (minutes is None or not algorithm.learning_curve):
            raise ValueError(f"mpcpearl_jax.train: {name} applies to an MPC-PEARL time budget")
    if opts.eval_minutes is not None and not opts.eval_minutes > 0:
        raise ValueError(
            f"mpcpearl_jax.train: eval_minutes must be positive, got {opts.eval_minutes}"
        )
    if opts.resume and opts.policy_only:
        raise ValueError(
            "mpcpearl_jax.train: resume continues from a checkpoint: not with policy_only"
        )
    return algorithm
