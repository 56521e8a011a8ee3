"""Scoring evaluated episodes: per-task metrics, how episodes ended, pooling over task sets.

`per_task_metrics` turns the arrays of an evaluation
(`mpcpearl_jax.evaluation.evaluate.make_evaluator`, the
GP-MPC rollout, training-style episodes) into the per-seed, per-task method §8 metrics and the
first contact of each episode (`metrics.first_contact`); `failures` counts how the episodes of
one or more such records ended; `pooled` pools the per-task metrics of several task sets (mean,
standard error over tasks, the mean of each set). `experiments.evaluate` writes them into its
results.json records.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.envs.types import NavConfig, TaskParams
from mpcpearl_jax.evaluation.metrics import METRIC_NAMES, metric_values


@functools.partial(jax.jit, static_argnums=(4, 5))
def _first_contacts(position, collision, in_goal, tasks, robot_radius, human_radius):
    """`metrics.first_contact` of every episode [S, N] (compiled once per shape and radii)."""
    from mpcpearl_jax.evaluation import metrics

    one = lambda p, c, g, k: metrics.first_contact(p, c, g, k, robot_radius, human_radius)
    return jax.vmap(jax.vmap(one), in_axes=(0, 0, 0, None))(position, collision, in_goal, tasks)


def per_task_metrics(result: dict, tasks: TaskParams, cfg: NavConfig) -> dict[str, list]:
    """Per seed and task [S][N]: success, collision_free, TT, SPL, MGD, return, and the first
    contact of each episode (`metrics.first_contact`): its step (-1: none), whether the nearer
    obstacle was a person, the steps in contact, whether the goal was reached after it."""
    from mpcpearl_jax.evaluation import evaluate as eval_lib

    m = eval_lib.episode_metrics(result, tasks, cfg.robot_radius)
    c = _first_contacts(
        result["position"],
        result["collision"],
        result["in_goal"],
        tasks,
        cfg.robot_radius,
        cfg.human_radius,
    )
    out = {k: np.asarray(v, float) for k, v in metric_values(m).items()}
    out |= {
        "return": np.asarray(result["return"], float),
        "contact_step": np.asarray(c.step, int),
        "contact_person": np.asarray(c.with_person, float),
        "contact_steps": np.asarray(c.steps_in_contact, int),
        "reached_after_contact": np.asarray(c.reached_after, float),
    }
    return {k: v.tolist() for k, v in out.items()}


def failures(per_task: list[dict]) -> dict[str, Any]:
    """How the episodes of one or more `per_task` records ended: reached the goal without
    contact, contact (first with a person / a static obstacle; goal reached after it anyway),
    neither (time ran out), and the median step of the first contact."""
    col = lambda k: np.concatenate([np.asarray(p[k], float).ravel() for p in per_task])
    step, person, success = col("contact_step"), col("contact_person"), col("SR")
    hit = step >= 0
    return {
        "episodes": int(step.size),
        "success": int(success.sum()),
        "contact": int(hit.sum()),
        "contact_person": int((hit & (person > 0)).sum()),
        "contact_static": int((hit & (person == 0)).sum()),
        "reached_goal_after_contact": int(col("reached_after_contact").sum()),
        "timeout": int((~hit & (success == 0)).sum()),
        "median_first_contact_step": float(np.median(step[hit])) if hit.any() else None,
    }


def failure_line(f: dict) -> str:
    return (
        f"episodes {f['episodes']}: {f['success']} reached the goal without contact, "
        f"{f['contact']} with a contact (first with a person {f['contact_person']}, with a "
        f"static obstacle {f['contact_static']}; goal reached after it "
        f"{f['reached_goal_after_contact']}; "
        f"median first-contact step {f['median_first_contact_step']}), {f['timeout']} out of time"
    )


def pooled(records: list[dict]) -> dict:
    """Pool per-task metrics of several task sets: mean, standard error over tasks (each task's
    value averaged over the policy seeds) and the mean of each task set."""
    out: dict[str, Any] = {}
    for k in (*METRIC_NAMES, "return"):
        per_set = [np.asarray(r["per_task"][k], float).mean(axis=0) for r in records]
        allv = np.concatenate(per_set)
        se = float(allv.std(ddof=1) / np.sqrt(allv.size)) if allv.size > 1 else float("nan")
        out[k] = {
            "mean": float(allv.mean()),
            "se": se,
            "per_task_seed": [float(v.mean()) for v in per_set],
        }
    return out
