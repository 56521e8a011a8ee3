"""Reporting, in one place: the paper's numbers, run labels, results tables and learning curves.

Used by `run` (a run's final table and curves), `grbal.run`, `lab.compare` (several runs
side by side) and `experiments.gp_mpc` (the GP-MPC baseline next to the paper's column).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mpcpearl_jax.evaluation.metrics import METRIC_NAMES, METRICS, format_metric

# method §8: the paper's numbers (restaurant: 24 unseen tasks after two adaptation episodes).
PAPER = {
    "restaurant": {
        "PEARL": {"SR": 0.36, "TT": 64.32, "CFR": 0.99, "SPL": 0.31, "MGD": 33.59},
        "GP-MPC": {"SR": 0.67, "TT": 59.62, "CFR": 0.83, "SPL": 0.63, "MGD": 30.13},
        "MPC-SAC": {"SR": 0.17, "TT": 73.33, "CFR": 0.69, "SPL": 0.14, "MGD": 74.90},
        "MPC-PEARL 0.2": {"SR": 0.92, "TT": 38.61, "CFR": 0.99, "SPL": 0.78, "MGD": 22.16},
        "MPC-PEARL 0.2 (online)": {"SR": 0.83, "TT": 51.65, "CFR": 0.90, "SPL": 0.65, "MGD": 45.79},
    },
    "sidewalk": {
        "MPC-PEARL 0.2 (online)": {"SR": 0.67, "TT": 211.35, "SPL": 0.44},
        "GP-MPC": {"SR": 0.48},
        "PEARL (online)": {"SR": 0.03, "TT": 249.61, "CFR": 0.84, "SPL": 0.03},
    },
}
# method §9 (the authors' logs): how the paper's restaurant agents were trained, said beside its
# numbers wherever they are printed (the paper gives no training time for the sidewalk)
PAPER_TRAINING = {
    "restaurant": {"iterations": 3000, "updates_per_iteration": 750, "hours": 27, "seeds": 7},
}


def paper_training(env: str) -> str:
    """How the paper's agents of family `env` were trained, in words ('' where unknown)."""
    t = PAPER_TRAINING.get(env)
    if t is None:
        return ""
    steps = t["iterations"] * t["updates_per_iteration"]
    return (
        f"{t['iterations']} iterations x {t['updates_per_iteration']} gradient steps "
        f"({steps / 1e6:.2f}M), about {t['hours']} h on the authors' GPU machine, mean over "
        f"{t['seeds']} seeds"
    )


def run_label(cfg: Any) -> str:
    """The method's name of a run config (an ExperimentConfig, or a config.json dict, GrBAL's
    included): MPC-PEARL 0.2, PEARL, MPC-SAC 0.2, SAC or GrBAL."""
    d = cfg if isinstance(cfg, dict) else dataclasses.asdict(cfg)
    if d.get("method") == "grbal":  # written by experiments.grbal
        return "GrBAL"
    eps, context = d["train"]["eps"], d["pearl"]["use_context"]
    if eps == 0:
        return "PEARL" if context else "SAC"
    return f"{'MPC-PEARL' if context else 'MPC-SAC'} {eps:g}"


def metrics_table(columns: Sequence[tuple[str, dict]]) -> str:
    """Markdown table, one row per metric (SR, TT, CFR, SPL, MGD), one column per (name,
    metrics dict); '-' where a column lacks a metric."""
    lines = [
        "| metric | " + " | ".join(c for c, _ in columns) + " |",
        "|---|" + "---|" * len(columns),
    ]
    for m in METRIC_NAMES:
        cells = ["-" if d.get(m) is None else format_metric(m, d[m]) for _, d in columns]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def paper_columns(paper: dict) -> list[tuple[str, dict]]:
    return [(f"paper {k}", v) for k, v in paper.items()]


# each metric spelled out for a reader (`metrics.METRICS` computes them and says which way is
# better; method §8): what the results table prints under itself, and the README says
METRIC_LEGEND = {
    "SR": "success rate: share of episodes that reach the goal without a collision",
    "TT": "time to goal: steps of the episode spent outside the goal radius, the whole episode "
    "when the goal is never reached",
    "CFR": "collision-free rate: share of episodes without a collision",
    "SPL": "success weighted by path length: success x straight-line distance / distance driven",
    "MGD": "mean goal distance: squared distance to the goal (m^2) averaged over the episode's "
    "steps",
}


def metric_legend(online: bool = True, ood: bool = False, adapt_episodes: int = 2) -> str:
    """The lines under a results table: each metric, and what the columns' suffixes mean."""
    width = max(len(m) for m in METRIC_NAMES)
    lines = [
        f"{m:<{width}}  {METRIC_LEGEND[m]} "
        f"({'higher' if METRICS[m].higher_is_better else 'lower'} is better)"
        for m in METRIC_NAMES
    ]
    cols = [f"a bare column: the test tasks, each after {adapt_episodes} adaptation episodes"]
    if online:
        cols.append("(online): adapting within the one scored episode, no earlier episode")
    if ood:
        cols.append(
            "(OOD): out-of-distribution tasks, unlike any seen in training (shifted layouts "
            f"or crowds), after {adapt_episodes} adaptation episodes"
        )
    return "\n".join([*lines, "columns: " + "; ".join(cols)])


def results_table(results: dict[str, Any]) -> str:
    """One run's results.json: adaptation / online / OOD next to the paper's columns, each
    metric and column spelled out under it (`metric_legend`), and a line saying where the
    paper's columns come from and how long its agents trained."""
    label = results["label"]
    cols = [(f"{label}", results["test_adapt"]), (f"{label} (online)", results["test_online"])]
    ood = "SR" in results.get("ood_adapt", {})
    if ood:
        cols.append((f"{label} (OOD)", results["ood_adapt"]))
    paper = results.get("paper", {})
    adapt = results.get("config", {}).get("train", {}).get("eval_adapt_episodes", 2)
    table = metrics_table(cols + paper_columns(paper))
    table = f"{table}\n{metric_legend(online=True, ood=ood, adapt_episodes=adapt)}"
    if not paper:
        return table
    trained = paper_training(results.get("env", ""))
    note = "paper columns: the paper's published table" + (f" ({trained})" if trained else "")
    return f"{table}\n{note}"


def comparison_table(results: Sequence[tuple[str, dict]], paper: dict) -> str:
    """Several runs (label, results.json) side by side, then the paper's columns."""
    cols = []
    for label, res in results:
        cols.append((f"{label} (2 adapt. eps.)", res["test_adapt"]))
        cols.append((f"{label} (online)", res["test_online"]))
    return metrics_table(cols + paper_columns(paper))


def plot_learning_curves(
    runs: Sequence[tuple[str, list[dict]]], path: Path, saved_last: bool = False
) -> Path | None:
    """Train return, test return, SR and CFR against iteration for each (label, metrics rows)
    (a legend when there are several); None when there is nothing to plot. `saved_last`, for
    one run: mark the policy the run saved and evaluated (policy.msgpack, results.json), the
    last iteration's (a dashed line there), so that a last point below an earlier one reads as
    what it is, not as a regression of the saved result."""
    if not any(rows for _, rows in runs):
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.5))
    for label, rows in runs:
        axes[0].plot([r["iteration"] for r in rows], [r["train_return"] for r in rows], lw=1)
        ev = [r for r in rows if "test_SR" in r]
        x = [r["iteration"] for r in ev]
        for ax, key in zip(axes[1:], ("test_return", "test_SR", "test_CFR"), strict=True):
            ax.plot(x, [r[key] for r in ev], marker="o", ms=3, label=label)
    titles = ("train return (posterior episodes)", "test return", "test SR", "test CFR")
    for ax, title in zip(axes, titles, strict=True):
        ax.set_title(title)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    if len(runs) > 1:
        axes[1].legend()
    last = max((r["iteration"] for _, rows in runs for r in rows), default=0)
    note = ""
    if saved_last:
        for ax in axes[1:]:
            ax.axvline(last, color="k", ls="--", lw=0.8)
        note = f"dashed line: the saved policy, the last iteration's ({last}), not the best point"
    if note:
        fig.suptitle(note, fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.94) if note else None)
    from mpcpearl_jax.envs.drawing import save_figure

    try:
        save_figure(fig, path, dpi=110)  # whole or not there: a stop leaves no cut-short PNG
    finally:
        plt.close(fig)
    return path
