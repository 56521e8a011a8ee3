"""GrBAL on the run session: its `RunKind` (`GRBAL`), its rules (`train_iterations`) and its
final evaluation (results.json, curves and figures: the files `mpcpearl_jax.runfolder` names,
so `lab.compare` reads both methods). `mpcpearl_jax.train` runs it for a GrBAL config (the
command: `python -m experiments.grbal`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import jax
import numpy as np

from mpcpearl_jax.errors import CheckpointError
from mpcpearl_jax.evaluation.metrics import METRIC_NAMES
from mpcpearl_jax.evaluation.report import PAPER, plot_learning_curves
from mpcpearl_jax.grbal.config import GrbalConfig, GrbalExperimentConfig
from mpcpearl_jax.grbal.trainer import GrbalState, GrbalTrainer
from mpcpearl_jax.runfolder import CONFIG_FILE, LOG_FILE, read_log, write_json
from mpcpearl_jax.training.loop import Progress
from mpcpearl_jax.training.resources import (
    _size,
    check_fits,
    dataclass_defaults,
    grown_fields,
    tree_bytes,
)
from mpcpearl_jax.training.run import Session

LABEL = "GrBAL"
# The paper prints no GrBAL numbers (its restaurant bar charts only); its text (Sec. IV-A):
PAPER_NOTE = (
    "paper GrBAL (restaurant): no numbers printed (bar charts only); 'GrBAL presents the worst "
    "performance in terms of all metrics', slightly below MPC-SAC (SR 0.17, TT 73.33, CFR 0.69, "
    "SPL 0.14, MGD 74.90)"
)


def load_config(run_dir: Path) -> GrbalExperimentConfig:
    path = run_dir / CONFIG_FILE
    if not path.is_file():
        raise CheckpointError(f"{path}: no config.json; is this a run directory?")
    try:
        return GrbalExperimentConfig.from_dict(json.loads(path.read_text()))
    except (json.JSONDecodeError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: not a GrBAL run config ({e})") from e


def load_model(run_dir: Path, data: str | None = None) -> tuple[GrbalTrainer, dict]:
    """A GrBAL run's trainer (built from its config.json; `data` replaces the run's data file)
    and what its policy.msgpack holds: {"model": parameters, "norm": input normalisation}, every
    leaf with a leading seed axis. CheckpointError naming the file when it is missing, does not
    match the config's model, or holds NaN or inf."""
    from flax import serialization

    from mpcpearl_jax.runfolder import POLICY_FILE, non_finite_leaves

    run_dir = Path(run_dir)
    cfg = load_config(run_dir)
    if data is not None:
        cfg = dataclasses.replace(cfg, data=data)
    trainer = GrbalTrainer(cfg)
    path = run_dir / POLICY_FILE
    if not path.is_file():
        raise CheckpointError(f"{path}: no saved model (the run has not saved one yet)")
    shapes = jax.eval_shape(trainer._init_state)
    target = {"model": shapes.params, "norm": shapes.norm}
    try:
        saved = serialization.from_bytes(target, path.read_bytes())
    except (ValueError, TypeError, KeyError) as e:
        raise CheckpointError(f"{path}: not this run's GrBAL model ({e})") from e
    want = [(x.shape, x.dtype) for x in jax.tree_util.tree_leaves(target)]
    got = [(np.shape(x), np.asarray(x).dtype) for x in jax.tree_util.tree_leaves(saved)]
    if want != got:
        raise CheckpointError(f"{path}: its arrays do not match the model of {CONFIG_FILE}")
    bad = non_finite_leaves(saved)
    if bad:
        raise CheckpointError(f"{path}: NaN or inf in {len(bad)} array(s), e.g. {bad[0]}")
    return trainer, saved


def _eval_row(trainer: GrbalTrainer, state: GrbalState) -> dict[str, Any]:
    """test_* = the headline evaluation (online on the sidewalk, after adaptation otherwise),
    test_online_* / test_adapt_* = both."""
    both = trainer.evaluate_both(state)
    row: dict[str, Any] = {}
    for mode, ev in both.items():
        row.update({f"test_{mode}_{k}": v for k, v in ev.items() if k in _ROW_KEYS})
    head = both["online" if trainer.cfg.online_eval else "adapt"]
    row.update({f"test_{k}": v for k, v in head.items() if k in _ROW_KEYS})
    return row


_ROW_KEYS = (*METRIC_NAMES, "return")


class GrbalRun:
    """GrBAL's `training.run.RunKind`: `GrbalTrainer`, its dynamics model in policy.msgpack,
    iterations and checkpoints in the `grbal` section."""

    section = "grbal"
    network_file = False

    def load_config(self, run_dir: Path, resume: bool) -> GrbalExperimentConfig:
        return load_config(run_dir)

    def make_trainer(self, cfg: GrbalExperimentConfig) -> GrbalTrainer:
        return GrbalTrainer(cfg)

    def check_fits(self, trainer: GrbalTrainer) -> None:
        _check_memory(trainer)

    def saved_params(self, trainer: GrbalTrainer, state: GrbalState) -> Any:
        return trainer.model_params(state)


GRBAL = GrbalRun()


def _check_memory(trainer: GrbalTrainer) -> None:
    """The state (model, optimizer, per-task buffers) and MPPI's sampled sequences (every env of
    a collection or an evaluation batch holds num_samples x plan_horizon actions, noise and
    costs) must fit in memory: ConfigError naming the fields otherwise, the model's width
    (grbal.hidden, when above its default) first when the model and its optimizer are the
    larger part."""
    g, seeds = trainer.cfg.grbal, trainer.cfg.seeds
    envs = seeds * max(
        g.tasks_per_iteration * g.episodes_per_task, int(trainer.test_tasks.start.shape[0])
    )
    planner = envs * g.num_samples * g.plan_horizon * (3 * 2 + 2) * 4
    shapes = jax.eval_shape(trainer.init_state)
    state = tree_bytes(shapes) // jax.process_count()
    model = (tree_bytes(shapes.params) + tree_bytes(shapes.opt_state)) // jax.process_count()
    data = "grbal.plan_horizon, grbal.num_samples, grbal.buffer_episodes or the seeds"
    width = grown_fields({"hidden": g.hidden}, dataclass_defaults(GrbalConfig), "grbal")
    parts = [data, *width] if state - model + planner >= model else [*width, data]
    what = "the state and the MPPI samples"
    if width:
        what += f" (model and optimizer {_size(model)}, the rest {_size(state - model + planner)})"
    check_fits(state + planner, what, ", or ".join(parts))


def train_iterations(
    sess: Session,
    on_row: Callable[[dict[str, Any]], None] | None = None,
    minutes: float | None = None,
    handle_sigint: bool = False,
) -> tuple[GrbalState | None, dict[str, Any]]:
    """GrBAL's rules on an open session: `grbal.iterations` iterations (or until `minutes` of
    this process have passed, if the iterations last longer: the run stops evaluated and
    checkpointed, resumable), evaluation every `eval_interval` iterations and at the end,
    checkpoints every `checkpoint_interval`; `on_row(row)` sees every row with its evaluation.

    Returns (state, info) as `training.run.train_iterations` does, info["stopped"] "done" or
    "budget" (the time ran out first). With handle_sigint, a stop signal (Ctrl-C, SIGTERM,
    SIGHUP) finishes the iteration under way, saves it and raises RunInterrupted
    (`Session.train`); a second one stops at once."""
    trainer = cast(GrbalTrainer, sess.trainer)  # a GrBAL session's (GrbalRun.make_trainer)
    g, done = sess.cfg.grbal, sess.done
    budget_s = None if minutes is None else 60.0 * minutes
    t_start = time.perf_counter()

    def out_of_time() -> bool:
        return budget_s is not None and time.perf_counter() - t_start >= budget_s

    decided: dict[int, bool] = {}  # the budget is read once per iteration

    def until(p: Progress) -> bool:
        if p.iterations not in decided:
            more_time = p.iterations == done or not out_of_time()
            decided[p.iterations] = p.iterations >= g.iterations or not more_time
        return decided[p.iterations]

    def evaluate(row: dict[str, Any], state: GrbalState, p: Progress) -> dict[str, Any] | None:
        fields = None
        if p.last or (g.eval_interval > 0 and p.iterations % g.eval_interval == 0):
            t0 = time.perf_counter()
            fields = {**_eval_row(trainer, state), "eval_s": time.perf_counter() - t0}
        if on_row is not None:
            on_row({**row, **(fields or {})})
        return fields

    state = sess.train(
        until=until,
        on_row=evaluate,
        checkpoint_after=lambda p, _: p.iterations % g.checkpoint_interval == 0,
        handle_sigint=handle_sigint,
    )
    p = sess.progress
    stopped = "budget" if p.iterations < g.iterations else "done"
    info = {"mode": "iterations", "stopped": stopped, "iterations": p.iterations, "lost": 0}
    info.update(saved=p.saved, train_s=p.train_s, first_iteration_s=p.first_iteration_s)
    return state, info


def final_evaluation(trainer: GrbalTrainer, state: GrbalState, out: str | Path) -> dict[str, Any]:
    """Test tasks (adaptation and online) and OOD tasks; results.json, curves and figures."""
    from mpcpearl_jax.envs import tasks_for

    run_dir = Path(out)
    cfg = trainer.cfg
    results: dict[str, Any] = {"label": LABEL, "env": cfg.env, "config": cfg.to_dict()}
    both, raw = trainer.evaluate_both_episodes(state)
    results["test_adapt"] = both["adapt"]
    results["test_online"] = both["online"]
    try:
        ood = tasks_for(cfg, "ood", config=trainer.env.config)
        results["ood_adapt"] = trainer.evaluate(state, tasks=ood)
    except (ValueError, FileNotFoundError) as e:  # no OOD split (or no OOD scenario file)
        results["ood_adapt"] = {"skipped": str(e)}
    results["paper"] = PAPER.get(cfg.env, {})
    no_result = "no GrBAL result in the paper"
    results["paper_note"] = PAPER_NOTE if cfg.env == "restaurant" else no_result
    plot_learning_curves([(LABEL, read_log(run_dir / LOG_FILE))], run_dir / "learning_curves.png")
    trajectory_figures(trainer, raw, run_dir)
    write_json(run_dir / "results.json", results)  # last: the run is finished once it is there
    return results


def trajectory_figures(trainer: GrbalTrainer, raw: dict, run_dir: Path, n: int = 4) -> None:
    """The first n test tasks, seed 0: the evaluated episode after adaptation and the online one."""
    from mpcpearl_jax.envs import save_trajectory

    for i in range(min(n, int(trainer.test_tasks.start.shape[0]))):
        task = jax.tree_util.tree_map(lambda x, i=i: x[i], trainer.test_tasks)
        paths = {
            f"GrBAL {mode}": (np.asarray(r["position"][0, i]), np.asarray(r["collision"][0, i]))
            for mode, r in raw.items()
        }
        path = run_dir / f"trajectory_test{i}.png"
        title = f"GrBAL, {trainer.cfg.env} test task {i}"
        save_trajectory(trainer.cfg.env, path, task, paths, trainer.env.config, title)
