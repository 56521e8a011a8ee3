"""Training on a wall-clock budget, with its learning curve: how good does the policy get in M
minutes of training? (`python -m experiments.restaurant --minutes M [--eval-minutes X]`, and
the sidewalk's command.)

`train_on_budget` runs the session's trainer (`run.Session.train`) until M minutes of training
have passed, counted from the start of the first iteration (its compilation included, and
reported on its own). Every X minutes of training (default M / 8; at most M / 2) and once more at
the end the policy is evaluated deterministically on the test tasks (the run's headline
protocol: adaptation, or online for the sidewalk; for reporting only) and on a validation set
that is not the test set (`envs.validation_tasks`). The clock stops while evaluating;
evaluation seconds are recorded separately. There is also an evaluation of the untrained policy
at minute 0.

Writes into the run folder: curve.json (config, machine, load average, eval points, time to the
first success and to SR 0.5 / 0.75 on test and val), curve.png, curve-points.jsonl (the eval
points so far) beside what every run writes (metrics.jsonl, config.json, the policy and training
state; `mpcpearl_jax.load_policy(out)` works) and what `run.final_evaluation` writes
(results.json, learning_curves.png, trajectory figures).

The training state is checkpointed every `train.checkpoint_interval` iterations and after every
evaluation, so a crash (kill -9) loses at most the work since then. Ctrl-C (or SIGTERM, SIGHUP)
saves and stops, and exits 130 (128 + the signal); `--resume` (the same options; --minutes may
grow) continues exactly: the curve points so far are kept and the budget counts the training
minutes already spent.

Train alone: other work on the machine slows every iteration down and so shifts the whole curve.
The 1-minute load average at the start is recorded, with a warning above LOAD_WARN.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mpcpearl_jax.evaluation.report import run_label
from mpcpearl_jax.runfolder import write_json
from mpcpearl_jax.training.stopping import stop_exit_code

METRICS = ("SR", "CFR", "TT", "SPL", "MGD", "return")
SPLITS = ("test", "val")
LOAD_WARN = 1.5  # 1-minute load average above which another job is probably running
# (name, metric, threshold, strict): the first eval point with metric > / >= threshold
TARGETS = (
    ("first_success", "SR", 0.0, True),
    ("SR_0.5", "SR", 0.5, False),
    ("SR_0.75", "SR", 0.75, False),
)
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
    """A warning on stderr when the 1-minute load average `load[0]` is above LOAD_WARN: another
    job would slow the whole curve."""
    if load is not None and load[0] > LOAD_WARN:
        print(
            f"warning: 1-minute load average {load[0]:.2f} > {LOAD_WARN}: another job is "
            "running; timings (and so the whole curve) will be slower than on a quiet machine",
            file=sys.stderr,
            flush=True,
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
    fig.savefig(path, dpi=110)
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


def _print_point(p: dict[str, Any]) -> None:
    print(
        f"[learning] {p['minutes']:7.2f} min  it {p['iteration']:6d}  grad {p['grad_steps']:8d}"
        f"  test SR {p['test_SR']:.2f} CFR {p['test_CFR']:.2f} ret {p['test_return']:8.1f}"
        f"  val SR {p['val_SR']:.2f} CFR {p['val_CFR']:.2f}  (eval {p['eval_s']:.1f} s)",
        flush=True,
    )


def train_for(
    sess,
    *,
    budget_s: float,
    every_s: float,
    val_tasks,
    online: bool = False,
    clock=time.perf_counter,
    on_point=_print_point,
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
    "diverged: ..." (then `state` is None: the failed or abandoned iteration consumed it; after
    "interrupted", `saved` is the iteration a resume starts from).
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

    state = sess.state
    if not points:
        evaluate(state, progress)  # the untrained policy at minute 0 (compiles the evaluator)
    try:
        state = sess.train(
            until=lambda p: p.train_s >= budget_s,
            on_row=lambda row, state, p: (
                evaluate(state, p) if p.last or p.train_s >= schedule["next_eval_s"] else None
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
        info["stopped"], state = f"diverged: {e}", None
        print(f"error: {e}", file=sys.stderr, flush=True)
    except RunInterrupted:  # Ctrl-C: saved at `progress.saved`
        info["stopped"], state = "interrupted", None
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


def train_on_budget(
    sess,
    *,
    minutes: float,
    eval_minutes: float | None = None,
    label: str,
    preset: str,
    argv: Sequence[str] = (),
    resumed: bool = False,
    policy_only: bool = False,
    load_start: list[float] | None = None,
    t_wall0: float | None = None,
    clock=time.perf_counter,
) -> int:
    """Train the open run session `sess` (`run.open_session(..., until_budget=True)`) for
    `minutes` of training with an eval point every `eval_minutes` (`eval_every_minutes`), write
    curve.json and curve.png, run the final evaluation and print the time-to-target table.
    `label` names the run in the record and the figures; `preset` and `argv` are recorded;
    `policy_only` saves policy.msgpack alone (no orbax checkpoint: no resume); `load_start` and
    `t_wall0` (`time.perf_counter()` before the session was opened) are recorded; `clock` times
    the training (tests give a fake one).

    Returns the command's exit code: 0 the budget was spent and the run evaluated, 1 training
    diverged or no iteration finished, 130 interrupted by Ctrl-C (saved; continue with
    --resume)."""
    import dataclasses

    from mpcpearl_jax.envs import validation_tasks
    from mpcpearl_jax.runfolder import LOG_FILE, POLICY_FILE, read_log, save_config, save_params
    from mpcpearl_jax.training.final import final_evaluation
    from mpcpearl_jax.training.machine import available_cores, machine_info, print_table
    from mpcpearl_jax.training.run import RunInterrupted, policy_params

    budget_s = minutes * 60.0
    every_s = eval_every_minutes(minutes, eval_minutes) * 60.0
    t_wall0 = time.perf_counter() if t_wall0 is None else t_wall0
    cfg, trainer, out = sess.cfg, sess.trainer, sess.run_dir
    online = cfg.online_eval
    build_s = time.perf_counter() - t_wall0
    val_tasks, val_set = validation_tasks(
        cfg, config=trainer.env.config, train_tasks=trainer.train_tasks
    )
    tc = cfg.train
    log_path, points_path = out / LOG_FILE, out / POINTS_FILE

    def save_policy(step: int, state) -> None:  # no orbax checkpoint (no --resume)
        save_params(out / POLICY_FILE, policy_params(state))

    state, points, info = train_for(
        sess,
        budget_s=budget_s,
        every_s=every_s,
        val_tasks=val_tasks,
        online=online,
        clock=clock,
        # as the training command: orbax checkpoint of the TrainState + policy.msgpack
        save=save_policy if policy_only else sess.save,
        checkpoint_every=tc.checkpoint_interval,
        handle_sigint=True,
        points=_restored_points(sess, points_path),
        points_path=points_path,
    )
    done, train_s, eval_s = info["iterations"], info["train_s"], info["eval_s"]
    stopped, first_iteration_s = info["stopped"], info["first_iteration_s"]
    saved = max(info["saved"], 0)
    if stopped == "interrupted":  # the curve as a resume will continue it
        done, points = saved, [p for p in points if p["iteration"] <= saved]
    load_end = _loadavg()
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
        "budget_minutes": minutes,
        "eval_every_minutes": every_s / 60.0,
        "eval_protocol": "online" if online else "adapt",
        "test_tasks": int(trainer.test_tasks.start.shape[0]),
        "val_tasks": int(val_tasks.start.shape[0]),
        "val_set": val_set,
        "stopped": stopped,
        "iterations": done,
        "updates_per_iteration": tc.updates_per_iteration,
        "grad_steps": done * tc.updates_per_iteration,
        "env_steps": env_steps(trainer, done),
        "resumed_at_iteration": sess.done if resumed else None,
        "timing": {
            "build_s": build_s,  # the trainer and its initial (or restored) state
            "first_iteration_s": first_iteration_s,
            "train_s": train_s,
            "eval_s": eval_s,
            "first_eval_s": points[0]["eval_s"],
        },
        "loadavg_start_1m_5m_15m": load_start,
        "loadavg_end_1m_5m_15m": load_end,
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
    rows = read_log(log_path)
    record["time_to"]["train"] = {
        "first_success": first_train_success(rows, tc.updates_per_iteration)
    }
    steady = [b["train_s"] - a["train_s"] for a, b in zip(rows, rows[1:], strict=False)]
    # compilation ~ first iteration minus a steady one (the first also does the initial collection)
    record["timing"]["iteration_s_median"] = statistics.median(steady) if steady else None
    curve_path = out / "curve.json"
    write_json(curve_path, record)
    plot_curve(points, out / "curve.png", f"{label}: {run_label(cfg)}, {minutes:g} min")
    if stopped == "interrupted":
        lost = info["iterations"] - saved
        line = str(RunInterrupted(saved, lost))
        if policy_only:
            line = f"interrupted at iteration {saved} (--policy-only: no checkpoint to resume from)"
        print(line, file=sys.stderr, flush=True)
        return stop_exit_code()
    if done == 0:
        print(f"error: no iteration finished; {curve_path} written", file=sys.stderr)
        return 1

    t = time.perf_counter()  # the last checkpoint was saved with the last evaluation
    if stopped == "budget":
        final_evaluation(trainer, state, out, label)
    record["timing"]["final_evaluation_s"] = time.perf_counter() - t
    record["timing"]["total_wall_s"] = time.perf_counter() - t_wall0
    write_json(curve_path, record)

    tm = record["timing"]
    print_table(
        summary_rows(record),
        ["split", "target", "minutes", "grad steps", "iteration"],
        title=f"{label}: time to target (training minutes, compile included)",
    )
    hit = record["time_to"]["train"]["first_success"]
    first = "never" if hit is None else f"{hit['minutes']:.2f} min"
    print(
        f"trained {train_s / 60:.2f} min ({done} iterations, {record['grad_steps']} gradient "
        f"steps, {record['env_steps']} env steps per seed; first iteration incl. compile "
        f"{first_iteration_s:.1f} s); evaluation {eval_s:.1f} s off the clock; first training "
        f"success: {first}; "
        f"final test SR {points[-1]['test_SR']:.2f}, val SR {points[-1]['val_SR']:.2f}; "
        f"total wall {tm['total_wall_s']:.1f} s",
        flush=True,
    )
    print(f"curve, policy and results in {out}", flush=True)
    return 0 if stopped == "budget" else 1
