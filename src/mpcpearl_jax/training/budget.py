"""Training on a wall-clock budget, with its learning curve: how good does the policy get in M
minutes of training? (`python -m experiments.restaurant --minutes M [--eval-minutes X]`, and
the sidewalk's command.)

`train_minutes` runs the session's trainer (`run.Session.train`) until M minutes of training
have passed, counted from the start of the first iteration (its compilation included, and
reported on its own). Every X minutes of training (default M / 8; at most M / 2) and once more at
the end the policy is evaluated deterministically on the test tasks (the run's headline
protocol: adaptation, or online for the sidewalk; for reporting only) and on a validation set
that is not the test set (`envs.validation_tasks`). The clock stops while evaluating;
evaluation seconds are recorded separately. There is also an evaluation of the untrained policy
at minute 0.

`write_curve` writes into the run folder (through `training.final.finish`): curve.json (config,
machine, load average, eval points, time to the first success and to SR 0.5 / 0.75 on test and val),
curve.png, curve-points.jsonl (the eval points so far) beside what every run writes (metrics.jsonl,
config.json, the policy and training state; `mpcpearl_jax.load_policy(out)` works) and what
`training.final.final_evaluation` writes (results.json, learning_curves.png, trajectory figures).

The training state is checkpointed every `train.checkpoint_interval` iterations and after every
evaluation, so a crash (kill -9) loses at most the work since then. Ctrl-C (or SIGTERM, SIGHUP)
saves and stops (info "stopped": "interrupted"; the command then exits 128 + the signal);
`--resume` (the same options; --minutes may grow) continues exactly: the curve points so far
are kept and the budget counts the training minutes already spent.

Train alone: other work on the machine slows every iteration down and so shifts the whole curve.
The 1-minute load average at the start is recorded, with a warning above LOAD_WARN.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mpcpearl_jax.evaluation.report import run_label
from mpcpearl_jax.runfolder import write_json

METRICS = ("SR", "CFR", "TT", "SPL", "MGD", "return")
SPLITS = ("test", "val")
LOAD_WARN = 1.5  # 1-minute load average above which another job is probably running
# (name, metric, threshold, strict): the first eval point with metric > / >= threshold
TARGETS = (
    ("first_success", "SR", 0.0, True),
    ("SR_0.5", "SR", 0.5, False),
    ("SR_0.75", "SR", 0.75, False),
)
CURVE_FILE = "curve.json"
POINTS_FILE = "curve-points.jsonl"  # one line per eval point, as metrics.jsonl (for --resume)


# ------------------------------------------------------------------- pure helpers
def time_to_threshold(
    points: Sequence[dict[str, Any]], key: str, threshold: float, strict: bool = False
) -> dict[str, Any] | None:
    """The first eval point with points[key] >= threshold (> if strict), as
    {"minutes", "grad_steps", "iteration", "value"}; None if no point reaches it.

    `points` are in training order; NaN or missing values never count.
    """
    for p in points:
        v = p.get(key)
        if v is None or (isinstance(v, float) and math.isnan(v)):
            continue
        if v > threshold or (not strict and v == threshold):
            return {
                "minutes": p["minutes"],
                "grad_steps": p["grad_steps"],
                "iteration": p["iteration"],
                "value": v,
            }
    return None


def time_to_targets(points: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """{split: {target: time_to_threshold(...)}} for the TARGETS on test and val."""
    return {
        split: {
            name: time_to_threshold(points, f"{split}_{metric}", thr, strict)
            for name, metric, thr, strict in TARGETS
        }
        for split in SPLITS
    }


def first_train_success(rows: Sequence[dict[str, Any]], updates_per_iteration: int):
    """The first iteration whose training episodes (posterior z, MPC infusion on) reached the
    goal without collision, from metrics.jsonl rows; None if none did."""
    for r in rows:
        if r.get("train_success", 0) > 0:
            return {
                "minutes": r["train_s"] / 60.0,
                "grad_steps": r["iteration"] * updates_per_iteration,
                "iteration": r["iteration"],
                "value": r["train_success"],
            }
    return None


def eval_every_minutes(minutes: float, eval_minutes: float | None) -> float:
    """Minutes of training between evaluations: default M / 8, at most M / 2."""
    every = minutes / 8 if eval_minutes is None else eval_minutes
    return min(every, minutes / 2)


def default_label(env: str, preset: str, algo: str, eps: float) -> str:
    return f"{env}-{preset}-{algo}-eps{eps:g}"


def _loadavg() -> list[float] | None:
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def load_at_start() -> list[float] | None:
    """The 1-, 5- and 15-minute load averages (None where the system has none)."""
    return _loadavg()


def warn_if_busy(load: list[float] | None) -> None:
    """A warning (`notices.warn`) when the 1-minute load average `load[0]` is above LOAD_WARN:
    another job would slow the whole curve."""
    from mpcpearl_jax.notices import warn

    if load is not None and load[0] > LOAD_WARN:
        warn(
            f"warning: 1-minute load average {load[0]:.2f} > {LOAD_WARN}: another job is "
            "running; timings (and so the whole curve) will be slower than on a quiet machine"
        )


# -------------------------------------------------------------------------- running
def _evaluate(trainer, state, val_tasks, online: bool) -> dict[str, float]:
    """test_* and val_* metrics of the policy."""
    row: dict[str, float] = {}
    for split, tasks in (("test", None), ("val", val_tasks)):
        ev = trainer.evaluate(state, tasks=tasks, online=online)
        row.update({f"{split}_{k}": ev[k] for k in METRICS})
    return row


def _train_logs(log: dict[str, Any] | None) -> dict[str, Any]:
    if log is None:
        return {}
    keep = ("mpc_fallbacks", "mpc_fallback_rate")
    return {k: v for k, v in log.items() if k.startswith("train_") or k in keep}


def plot_curve(points: Sequence[dict[str, Any]], path: Path, title: str) -> Path:
    """curve.png: SR, CFR and return on test and val against minutes (top) and gradient steps
    (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(14, 7), squeeze=False)
    for row, (xkey, xlabel) in enumerate(
        (
            ("minutes", "training minutes (compile included)"),
            ("grad_steps", "gradient steps (thousands)"),
        )
    ):
        scale = 1e-3 if xkey == "grad_steps" else 1.0
        x = [p[xkey] * scale for p in points]
        for ax, metric in zip(axes[row], ("SR", "CFR", "return"), strict=True):
            for split, style in (("test", "-o"), ("val", "--s")):
                ax.plot(x, [p[f"{split}_{metric}"] for p in points], style, ms=3, label=split)
            ax.set_title(metric)
            ax.set_xlabel(xlabel)
            ax.grid(alpha=0.3)
            if metric in ("SR", "CFR"):
                ax.set_ylim(-0.05, 1.05)
            ax.legend(fontsize=8)
    sub = "test: the unseen test tasks; val: the validation tasks"
    fig.suptitle(f"{title}\n{sub}", fontsize=10)
    fig.tight_layout()
    from mpcpearl_jax.envs.drawing import save_figure

    try:
        save_figure(fig, path, dpi=110)  # whole or not there: a stop leaves no cut-short PNG
    finally:
        plt.close(fig)
    return path


def summary_rows(record: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for split in SPLITS:
        for name, _, _, _ in TARGETS:
            hit = record["time_to"][split][name]
            rows.append(
                {
                    "split": split,
                    "target": name,
                    "minutes": "never" if hit is None else round(hit["minutes"], 2),
                    "grad steps": "-" if hit is None else hit["grad_steps"],
                    "iteration": "-" if hit is None else hit["iteration"],
                }
            )
    return rows


def env_steps(trainer, iterations: int) -> int:
    """Environment steps collected per seed after `iterations` (initial collection included)."""
    if iterations == 0:
        return 0
    tc, horizon = trainer.cfg.train, trainer.horizon
    per_iter = min(tc.tasks_per_iteration, trainer.num_train)
    per_iter *= (tc.prior_episodes + tc.posterior_episodes) * horizon
    return trainer.num_train * tc.initial_episodes * horizon + iterations * per_iter


def train_for(
    sess,
    *,
    budget_s: float,
    every_s: float,
    val_tasks,
    online: bool = False,
    clock=time.perf_counter,
    on_point=None,
    on_row=None,
    save=None,
    checkpoint_every: int = 0,
    handle_sigint: bool = False,
    points: Sequence[dict[str, Any]] = (),
    points_path: Path | None = None,
) -> tuple[Any, list[dict[str, Any]], dict[str, Any]]:
    """The learning curve's rules on a run session (`mpcpearl_jax.training.run.Session`): train
    until `budget_s` seconds of `trainer.iteration` calls have passed; evaluate at 0, every
    `every_s` training seconds and at the end (evaluation is off the clock).

    The session writes one line per iteration to metrics.jsonl (and TensorBoard); one line per
    eval point goes to `points_path`. `save(iteration, state)` (e.g. `sess.save`) checkpoints
    every `checkpoint_every` iterations, after every evaluation and when stopping on Ctrl-C
    (`handle_sigint`). `points` are the eval points of an earlier process, continued from the
    session's restored progress. Returns (state, eval points, info) with info = {iterations,
    saved, train_s, eval_s, first_iteration_s, stopped}; stopped is "budget", "interrupted" or
    "diverged: ..." (then `state` is None: the failed or abandoned iteration consumed it, and
    info["error"] is the exception; after "interrupted", `saved` is the iteration a resume starts
    from). `on_point(point)` sees each eval point as it is made (the command prints it);
    `on_row(row)` every iteration's metrics row, with the evaluation's fields when it evaluated.
    """
    from mpcpearl_jax.errors import TrainingDiverged
    from mpcpearl_jax.runfolder import append_log
    from mpcpearl_jax.training.run import RunInterrupted

    trainer = sess.trainer
    ups = trainer.cfg.train.updates_per_iteration
    points = list(points)
    progress = sess.progress
    info: dict[str, Any] = {"eval_s": sum(p["eval_s"] for p in points), "stopped": "budget"}
    t_loop0 = clock() - progress.wall_s0
    schedule = {"next_eval_s": (math.floor(progress.train_s / every_s) + 1) * every_s}

    def evaluate(state, p) -> dict[str, Any]:
        t = clock()
        row = _evaluate(trainer, state, val_tasks, online)
        dt = clock() - t
        info["eval_s"] += dt
        done = p.iterations
        point = {
            "minutes": p.train_s / 60.0,
            "wall_minutes": (clock() - t_loop0) / 60.0,
            "iteration": done,
            "grad_steps": done * ups,
            "env_steps": env_steps(trainer, done),
            "eval_s": dt,
            **row,
            **_train_logs(p.log),
        }
        points.append(point)
        if points_path is not None:
            append_log(points_path, point)
        if on_point is not None:
            on_point(point)
        schedule["next_eval_s"] = (math.floor(p.train_s / every_s) + 1) * every_s
        fields = {k: v for k, v in point.items() if k.startswith(("test_", "val_"))}
        return {**fields, "eval_s": dt}

    def report(row, fields):  # the caller's on_row sees every row, with its evaluation's fields
        if on_row is not None:
            on_row({**row, **(fields or {})})
        return fields

    state = sess.state
    if not points:
        evaluate(state, progress)  # the untrained policy at minute 0 (compiles the evaluator)
    try:
        state = sess.train(
            until=lambda p: p.train_s >= budget_s,
            on_row=lambda row, state, p: report(
                row, evaluate(state, p) if p.last or p.train_s >= schedule["next_eval_s"] else None
            ),
            checkpoint_after=lambda p, evaluated: (
                evaluated or bool(checkpoint_every and p.iterations % checkpoint_every == 0)
            ),
            save=save,
            handle_sigint=handle_sigint,
            clock=clock,
        )
        if points[-1]["iteration"] != progress.iterations:  # resumed at the end of the budget
            evaluate(state, progress)
    except TrainingDiverged as e:
        info["stopped"], info["error"], state = f"diverged: {e}", e, None
    except RunInterrupted as e:  # Ctrl-C: saved at `progress.saved`
        info["stopped"], info["error"], state = "interrupted", e, None
    info.update(
        iterations=progress.iterations,
        saved=progress.saved,
        train_s=progress.train_s,
        first_iteration_s=progress.first_iteration_s,
    )
    return state, points, info


def _restored_points(sess, points_path: Path) -> list[dict[str, Any]]:
    """The eval points up to the restored checkpoint (none for a new run); curve-points.jsonl
    is cut back to them."""
    from mpcpearl_jax.runfolder import atomic_write, read_log

    points = read_log(points_path, sess.done) if sess.done or sess.saved >= 0 else []
    atomic_write(points_path, "".join(json.dumps(p) + "\n" for p in points))
    return points


def train_minutes(
    sess,
    *,
    minutes: float,
    eval_minutes: float | None = None,
    policy_only: bool = False,
    on_point=None,
    on_row=None,
    clock=time.perf_counter,
) -> tuple[Any, dict[str, Any]]:
    """The minutes mode: train the open run session `sess` (`run.open_session(...,
    until_budget=True)`) for `minutes` of training with an eval point every `eval_minutes`
    (`eval_every_minutes`) on the test and validation tasks; a stop signal saves and stops.
    `policy_only` saves policy.msgpack alone (no orbax checkpoint: no resume); `on_point` sees
    each eval point, `on_row` every iteration's metrics row; `clock` times the training (tests
    give a fake one). Prints nothing.

    Returns (state, info): `train_for`'s info with `iterations` those a resume continues from,
    `lost` the iterations finished after the last checkpoint of an interrupted run, `points` the
    curve's eval points up to them, and what `write_curve` records (mode, minutes, every_s,
    val_tasks, val_set, policy_only). `training.final.finish` writes the results."""
    from mpcpearl_jax.envs import validation_tasks
    from mpcpearl_jax.runfolder import POLICY_FILE, save_params
    from mpcpearl_jax.training.run import policy_params

    cfg, trainer, out = sess.cfg, sess.trainer, sess.run_dir
    every_s = eval_every_minutes(minutes, eval_minutes) * 60.0
    val_tasks, val_set = validation_tasks(
        cfg, config=trainer.env.config, train_tasks=trainer.train_tasks
    )
    points_path = out / POINTS_FILE

    def save_policy(step: int, state) -> None:  # no orbax checkpoint (no --resume)
        save_params(out / POLICY_FILE, policy_params(state))

    state, points, info = train_for(
        sess,
        budget_s=minutes * 60.0,
        every_s=every_s,
        val_tasks=val_tasks,
        online=cfg.online_eval,
        clock=clock,
        on_point=on_point,
        on_row=on_row,
        # as the training command: orbax checkpoint of the TrainState + policy.msgpack
        save=save_policy if policy_only else sess.save,
        checkpoint_every=cfg.train.checkpoint_interval,
        handle_sigint=True,
        points=_restored_points(sess, points_path),
        points_path=points_path,
    )
    info["lost"] = 0
    if info["stopped"] == "interrupted":  # the curve as a resume will continue it
        saved = max(info["saved"], 0)
        info["lost"] = info["iterations"] - saved
        info["iterations"], points = saved, [p for p in points if p["iteration"] <= saved]
    info.update(
        mode="minutes",
        minutes=minutes,
        every_s=every_s,
        val_tasks=int(val_tasks.start.shape[0]),
        val_set=val_set,
        policy_only=policy_only,
        points=points,
    )
    return state, info


def write_curve(
    sess,
    info: dict[str, Any],
    *,
    label: str,
    preset: str = "",
    argv: Sequence[str] = (),
    resumed: bool = False,
    load_start: list[float] | None = None,
    build_s: float | None = None,
) -> dict[str, Any]:
    """config.json as run (train.iterations: those done, which a --resume continues from),
    curve.json (the record of `train_minutes`'s `info`: config, machine, load average, eval
    points, time to the first success and to SR 0.5 / 0.75 on test and val) and curve.png.
    `label` names the run in the record and the figure; `preset` and `argv` are recorded;
    `load_start` and `build_s` (the seconds the session took to open: the trainer and its initial
    or restored state) too.
    Returns the record."""
    import dataclasses

    from mpcpearl_jax.runfolder import LOG_FILE, read_log, save_config
    from mpcpearl_jax.training.machine import available_cores, machine_info

    cfg, trainer, out = sess.cfg, sess.trainer, sess.run_dir
    done, points, tc = info["iterations"], info["points"], cfg.train
    if done:  # the config as run: iterations = those done (a --resume continues from here)
        cfg = cfg.replace(train=dataclasses.replace(cfg.train, iterations=done))
        trainer.cfg = cfg  # only train.iterations differs, which the trainer never reads
    save_config(out, cfg)
    record: dict[str, Any] = {
        "label": label,
        "algo": run_label(cfg),
        "env": cfg.env,
        "preset": preset,
        "argv": list(argv),
        "budget_minutes": info["minutes"],
        "eval_every_minutes": info["every_s"] / 60.0,
        "eval_protocol": "online" if cfg.online_eval else "adapt",
        "test_tasks": int(trainer.test_tasks.start.shape[0]),
        "val_tasks": info["val_tasks"],
        "val_set": info["val_set"],
        "stopped": info["stopped"],
        "iterations": done,
        "updates_per_iteration": tc.updates_per_iteration,
        "grad_steps": done * tc.updates_per_iteration,
        "env_steps": env_steps(trainer, done),
        "resumed_at_iteration": sess.done if resumed else None,
        "timing": {
            "build_s": build_s,  # the trainer and its initial (or restored) state
            "first_iteration_s": info["first_iteration_s"],
            "train_s": info["train_s"],
            "eval_s": info["eval_s"],
            "first_eval_s": points[0]["eval_s"],
        },
        "loadavg_start_1m_5m_15m": load_start,
        "loadavg_end_1m_5m_15m": _loadavg(),
        "load_warning": bool(load_start and load_start[0] > LOAD_WARN),
        "machine": machine_info(),
        "threads": {
            "cores_available": available_cores(),
            **{
                v: os.environ.get(v)
                for v in ("XLA_FLAGS", "OMP_NUM_THREADS", "JAX_PLATFORMS")
                if os.environ.get(v)
            },
        },
        "config": cfg.to_dict(),
        "time_to": time_to_targets(points),
        "points": points,
    }
    rows = read_log(out / LOG_FILE)
    record["time_to"]["train"] = {
        "first_success": first_train_success(rows, tc.updates_per_iteration)
    }
    steady = [b["train_s"] - a["train_s"] for a, b in zip(rows, rows[1:], strict=False)]
    # compilation ~ first iteration minus a steady one (the first also does the initial collection)
    record["timing"]["iteration_s_median"] = statistics.median(steady) if steady else None
    write_json(out / CURVE_FILE, record)
    title = f"{label}: {run_label(cfg)}, {info['minutes']:g} min"
    plot_curve(points, out / "curve.png", title)
    return record
