"""The end of a training: `finish` (a time budget's learning curve, then the final
evaluation) and MPC-PEARL's final evaluation, `final_evaluation`: the test tasks (adaptation and
online) and the OOD tasks of the run's own task source, written into its folder as
results.json, the learning curves, trajectory figures and an animated episode. Each registered
algorithm (`mpcpearl_jax.algorithms`) names its final evaluation; `mpcpearl_jax.train`
(`mpcpearl_jax.api.train`) calls `finish` with it. Nothing here prints.

`TrainOptions` (`training.options`) is importable from here too.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.distributed import is_primary
from mpcpearl_jax.evaluation.report import PAPER, plot_learning_curves
from mpcpearl_jax.runfolder import LOG_FILE, read_log, write_json
from mpcpearl_jax.training.budget import CURVE_FILE, write_curve
from mpcpearl_jax.training.machine import machine_info
from mpcpearl_jax.training.options import TrainOptions
from mpcpearl_jax.training.run import Session
from mpcpearl_jax.training.trainer import Trainer, TrainState

__all__ = ["TrainOptions", "final_evaluation", "finish"]


def finish(
    sess: Session,
    state: Any,
    info: dict[str, Any],
    *,
    label: str,
    evaluate: Callable[[Any, Any, Path, str], dict[str, Any]] | None = None,
    t_wall0: float | None = None,
    **curve: Any,
) -> dict[str, Any] | None:
    """What a training writes once it stops (`info`: the mode's): a minutes run's learning curve
    (`budget.write_curve`, with `curve`'s fields recorded), then, once training is done (not
    interrupted, diverged or without an iteration), the final evaluation, `evaluate(trainer,
    state, run_dir, label)` (the algorithm's; MPC-PEARL's `final_evaluation` by default);
    the curve records how long that took and, from `t_wall0` (`time.perf_counter()` before the
    session was opened), the whole run. Returns results.json's content, or None where not
    evaluated; info["curve"] is the curve's record (minutes mode)."""
    record = None
    if info["mode"] == "minutes":
        record = info["curve"] = write_curve(sess, info, label=label, **curve)
    if info["stopped"] == "interrupted" or not info["iterations"]:
        return None
    t, results = time.perf_counter(), None
    if info["stopped"] in ("done", "budget"):
        run: Callable[..., dict[str, Any]] = evaluate or final_evaluation
        results = run(sess.trainer, state, sess.run_dir, label)
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
