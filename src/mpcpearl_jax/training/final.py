"""The final evaluation of a trained run: the test tasks (adaptation and online) and the OOD
tasks of the run's own task source, written into its folder as results.json, the learning
curves, trajectory figures and an animated episode, and printed beside the paper's table.

It is the last step of training: it evaluates through the trainer (`evaluate.make_evaluator`)
and reads the run folder's log (`runfolder`), both below it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.distributed import is_primary
from mpcpearl_jax.evaluation.report import PAPER, plot_learning_curves, results_table
from mpcpearl_jax.runfolder import LOG_FILE, read_log, write_json
from mpcpearl_jax.training.machine import machine_info
from mpcpearl_jax.training.trainer import Trainer, TrainState


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
    write_json(run_dir / "results.json", results)
    print(results_table(results))
    rows = read_log(run_dir / LOG_FILE)  # the saved policy is the last iteration's: marked
    plot_learning_curves([(label, rows)], run_dir / "learning_curves.png", saved_last=True)
    _trajectory_figure(trainer, raw, run_dir)
    _episode_gif(trainer, raw, run_dir, label)
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
