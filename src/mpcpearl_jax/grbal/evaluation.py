"""The evaluation of a GrBAL run folder as trained (`mpcpearl_jax.evaluate` reaches it through
the registered algorithm, `mpcpearl_jax.algorithms`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.evaluation.plan import EvaluationError, check_eval_seed, default_out, task_setup
from mpcpearl_jax.evaluation.runners import Setup


def evaluation_setup(run_dir: Path, **a: Any) -> tuple[Setup, int]:
    """The evaluation of a GrBAL run (`experiments.grbal`) as trained: its own controller, the
    learned model adapted as it acts, planned with MPPI (the protocol of its results.json);
    `a`: `mpcpearl_jax.evaluate`'s arguments. -> (the setup, the number of tasks). Registered
    as GrBAL's `Algorithm.evaluation_setup`."""
    from mpcpearl_jax.grbal.run import load_model

    given = [
        name
        for name, v in (
            ("controller", a["controller"] != "policy"),
            ("mpc", a["mpc"] or a["preset"] is not None),
            ("eps", a["eps"] is not None),
            ("episodes", a["episodes"] is not None),
            ("shield", a["shield"]),
            ("env", a["env"]),
        )
        if v
    ]
    if given:
        raise EvaluationError(
            f"{{{given[0]}}} does not apply to a GrBAL run (it is evaluated as trained)"
        )
    check_eval_seed(a["eval_seed"])
    data = str(a["data"]) if a["data"] else None
    try:
        trainer, saved = load_model(run_dir, data=data)
    except (ValueError, OSError) as e:  # a bad config, data file or task option
        raise EvaluationError(f"{run_dir}: {e}") from e
    cfg = trainer.cfg
    if cfg.data is not None and not Path(cfg.data).is_file():
        raise EvaluationError(
            f"data file {cfg.data} does not exist (the run's data file; pass {{data}} PATH)"
        )
    seeds, seed_index = cfg.seeds, a["seed_index"]
    if seed_index is not None and not 0 <= seed_index < seeds:
        raise EvaluationError(f"{{seed_index}} {seed_index}: the run has {seeds} seed(s)")
    seed_ids = list(range(seeds)) if seed_index is None else [seed_index]
    saved = jax.tree_util.tree_map(lambda x: np.asarray(x)[np.asarray(seed_ids)], saved)
    ts, options, tasks, task_ids, figure_ids, perturbation, n = task_setup(
        cfg,
        trainer.env,
        cfg.env,
        cfg.data,
        a["split"],
        task_seed=a["task_seed"],
        several_seeds=a["several_seeds"],
        scenarios=a["scenarios"],
        tasks=a["tasks"],
        figures=a["figures"],
        perturb=a["perturb"],
    )
    where = default_out(run_dir, "grbal", a["split"], a["online"], options, perturbation)
    s = Setup(
        controller="grbal",
        env_name=cfg.env,
        env_config=trainer.env.config,
        split=a["split"],
        task_seed=ts,
        data=cfg.data,
        tasks=tasks,
        task_ids=task_ids,
        figure_ids=figure_ids,
        out=where,
        label="GrBAL",
        run=run_dir,
        run_config=cfg,
        seed_ids=seed_ids,
        scenarios=options,
        perturbation=perturbation.label,
        grbal=(trainer, saved),
    )
    return s, n
