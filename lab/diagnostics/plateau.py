"""Why the first success from the task's start comes late: the committed training logs of the
main command's ten `default` seeds, the recommended recipe's five seeds and the learner screen's
arms, read without training anything.

    python -m lab.diagnostics.plateau            # figures + summary.json
    python -m lab.diagnostics.plateau --out DIR  # elsewhere

Per run it reads `config.json`, `metrics.jsonl` (one row per iteration: the posterior-phase
episodes' `train_success` from the task's start, `train_explore_success` from exploring starts,
`train_guide_success` from guided roll-ins, the MPC's share of steps, the critic's `q_mean`, the
policy's `log_pi`, the temperature `alpha`, the MPC solver's outcomes) and the final policy's
`eval/policy-val-seeds1-8/results.json` (how each of the 192 validation episodes ended). Lift-off
is the first iteration with `train_success > 0` (as in `lab.screen`). It writes
`summary.json` (every number per seed, group statistics, rank correlations of lift-off with the
first iterations' statistics) and five figures to `results/restaurant/plateau/`. The committed
evaluation records keep only the per-task SR and CFR: from them a run's validation outcomes are
null (its `val_SR` is still read) and `outcomes.png`, which draws them, is not written.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

OUT = Path("results/restaurant/plateau")
VAL8 = "eval/policy-val-seeds1-8/results.json"
EARLY = 20  # iterations 1-20: before any `default` seed's first success (the earliest is 38)
WINDOW = 10  # iterations either side of lift-off for the before/after comparison
AFTER = 30  # iterations from lift-off on kept for the aligned success curve
SCREEN_ARMS = ("guide", "nstep", "keep", "crossq", "mpcbuf")
# the runs read: group -> run folders (relative to the repository root), seed order
GROUPS: dict[str, list[str]] = {
    "default": ["results/restaurant/main-default"]
    + [f"results/restaurant/main-seeds/default-s{s}" for s in range(1, 10)],
    "recipe": [
        "results/restaurant/ablation/auto-entropy-24min",
        "results/restaurant/ablation/auto-entropy-seed1-24min",
    ]
    + [f"results/restaurant/seeds/mpc-pearl-s{s}" for s in range(2, 5)],
    **{a: [f"results/restaurant/screen/{a}-s{s}" for s in range(10)] for a in SCREEN_ARMS},
    # `default` with 95 iterations: seeds 2-9 resumed from the 75-iteration runs above
    "default_it95": [f"results/restaurant/main-seeds/default-it95-s{s}" for s in range(10)],
}
# the per-task arrays besides SR that the validation outcomes are read from
OUTCOME_ARRAYS = ("MGD", "contact_step", "contact_person", "reached_after_contact")
# per-iteration fields averaged over a window (absent ones are skipped)
FIELDS = (
    "train_success",
    "train_explore_success",
    "train_guide_success",
    "train_collision_free",
    "train_return",
    "train_mpc_share",
    "train_event_rate",
    "mpc_fallback_rate",
    "q_mean",
    "q_loss",
    "log_pi",
    "alpha",
)
# the first iterations' statistics correlated with the lift-off iteration
EARLY_FEATURES = (
    "q_mean_at_20",
    "log_pi_at_20",
    "alpha_at_20",
    "alpha_min",
    "alpha_min_iteration",
    "explore_success_1_20",
    "explore_successes_1_20",
    "collision_free_1_20",
    "return_1_20",
    "mpc_share_1_20",
    "event_rate_1_20",
    "fallback_rate_1_20",
    "q_loss_1_20",
)


class PlateauError(ValueError):
    """A run's records are missing or malformed; the message names the file (and line)."""


def read_metrics(path: Path) -> list[dict]:
    """The rows of a `metrics.jsonl`, in iteration order; blank lines are skipped."""
    if not path.is_file():
        raise PlateauError(f"{path}: no such file")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as e:
            raise PlateauError(f"{path}:{n}: not JSON ({e.msg})") from None
        if not isinstance(row, dict) or not isinstance(row.get("iteration"), int):
            raise PlateauError(f"{path}:{n}: a row needs an integer 'iteration'")
        rows.append(row)
    if not rows:
        raise PlateauError(f"{path}: no rows")
    its = [r["iteration"] for r in rows]
    if its != sorted(its) or len(set(its)) != len(its):
        raise PlateauError(f"{path}: iterations not strictly increasing")
    return rows


def read_json(path: Path) -> dict:
    if not path.is_file():
        raise PlateauError(f"{path}: no such file")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise PlateauError(f"{path}: not JSON ({e.msg})") from None


def series(rows: list[dict], key: str) -> np.ndarray:
    """A field over the iterations, NaN where a row lacks it."""
    return np.array([float(r[key]) if r.get(key) is not None else np.nan for r in rows])


def liftoff(rows: list[dict]) -> int | None:
    """The first iteration with a posterior-phase episode from the task's start that reached the
    goal without a collision (`train_success > 0`), None if none did."""
    return next((r["iteration"] for r in rows if (r.get("train_success") or 0) > 0), None)


def _mean(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.mean(x)) if x.size else None


def window_means(rows: list[dict]) -> dict[str, float | None]:
    return {k: _mean(series(rows, k)) for k in FIELDS if any(k in r for r in rows)}


def mpc_reasons(rows: list[dict]) -> dict[str, Any]:
    """The MPC solver's outcomes summed over rows: counts and shares of its calls."""
    tot: dict[str, int] = {}
    for r in rows:
        for k, v in (r.get("mpc_reasons") or {}).items():
            tot[k] = tot.get(k, 0) + int(v)
    n = sum(tot.values())
    return {"calls": n, **{f"share_{k}": v / n for k, v in sorted(tot.items())}} if n else {}


def row_counts(rows: list[dict], rows_per_iteration: int) -> dict[str, int]:
    """Posterior-phase episodes by start, and their successes, summed over rows (each row's
    shares times the rows collected per iteration, rounded)."""
    out = {"task_start": 0, "task_start_success": 0, "explore": 0, "explore_success": 0}
    guided = any("train_guide_rows" in r for r in rows)
    if guided:
        out.update(guide=0, guide_success=0)
    for r in rows:
        x = r.get("train_explore_rows") or 0.0
        g = r.get("train_guide_rows") or 0.0
        nx, ng = round(rows_per_iteration * x), round(rows_per_iteration * g)
        ns = rows_per_iteration - nx - ng
        out["task_start"] += ns
        out["task_start_success"] += round(ns * (r.get("train_success") or 0.0))
        out["explore"] += nx
        out["explore_success"] += round(nx * (r.get("train_explore_success") or 0.0))
        if guided:
            out["guide"] += ng
            out["guide_success"] += round(ng * (r.get("train_guide_success") or 0.0))
    return out


def early_features(rows: list[dict], rows_per_iteration: int) -> dict[str, float | None]:
    """Statistics of iterations 1-EARLY (`_1_20`: their mean; `_at_20`: iteration 20's value)."""
    head = [r for r in rows if r["iteration"] <= EARLY]
    at = {r["iteration"]: r for r in rows}.get(EARLY, {})
    alpha = series(rows, "alpha")
    ok = np.isfinite(alpha)
    imin = int(np.nanargmin(alpha)) if ok.any() else None
    return {
        "q_mean_at_20": at.get("q_mean"),
        "log_pi_at_20": at.get("log_pi"),
        "alpha_at_20": at.get("alpha"),
        "alpha_min": float(alpha[imin]) if imin is not None else None,
        "alpha_min_iteration": rows[imin]["iteration"] if imin is not None else None,
        "explore_success_1_20": _mean(series(head, "train_explore_success")),
        "explore_successes_1_20": row_counts(head, rows_per_iteration)["explore_success"],
        "collision_free_1_20": _mean(series(head, "train_collision_free")),
        "return_1_20": _mean(series(head, "train_return")),
        "mpc_share_1_20": _mean(series(head, "train_mpc_share")),
        "event_rate_1_20": _mean(series(head, "train_event_rate")),
        "fallback_rate_1_20": _mean(series(head, "mpc_fallback_rate")),
        "q_loss_1_20": _mean(series(head, "q_loss")),
    }


def q_turn(rows: list[dict]) -> dict[str, Any]:
    """The mean Q's lowest point (iteration and value) and its last value."""
    q = series(rows, "q_mean")
    if not np.isfinite(q).any():
        return {}
    i = int(np.nanargmin(q))
    return {"min_iteration": rows[i]["iteration"], "min": float(q[i]), "last": float(q[-1])}


def guide_curriculum(
    rows: list[dict], rows_per_iteration: int, h0: float | None
) -> dict[str, Any] | None:
    """The guide's roll-in bound h (`guide_h`) over training: the guided rows per iteration, h at
    iterations 10, 25 and 50, how many times it shrank and on how many guided rows each shrink
    was decided (the shrink after an iteration's collection is judged on that iteration's guided
    rows, and the logged h is the one after it; h0: the bound before the first iteration), and
    the guided rows' success."""
    if not any("guide_h" in r for r in rows):
        return None
    h = series(rows, "guide_h")
    g = series(rows, "train_guide_rows") * rows_per_iteration
    gs = series(rows, "train_guide_success")
    prev = np.concatenate([[h0 if h0 is not None else h[0]], h[:-1]])
    shrinks = np.flatnonzero(h < prev)
    at = {r["iteration"]: v for r, v in zip(rows, h.tolist(), strict=True)}
    return {
        "guided_rows_per_iteration": _mean(g),
        "h_at": {k: at.get(k) for k in (1, 10, 25, 50)},
        "h_zero_iteration": next(
            (r["iteration"] for r, v in zip(rows, h.tolist(), strict=True) if v == 0), None
        ),
        "shrinks": int(shrinks.size),
        "rows_behind_a_shrink": seed_stats([float(g[i]) for i in shrinks]),
        "guide_success_1_10": _mean(gs[:10]),
        "guide_success_11_30": _mean(gs[10:30]),
    }


def val_outcomes(record: dict) -> dict[str, Any]:
    """How the validation episodes ended, from the per-task arrays of every task set: reached
    the goal without contact; first contact with a person / a table (goal reached after it
    counted apart); out of time without either. MGD (the mean over steps of the squared distance
    to the goal) per outcome. None when no task set's per-task arrays go beyond SR and CFR (the
    committed evaluation records keep only those two): the outcomes are not recorded there."""
    records = record.get("records", [])
    if records and not any(k in rec.get("per_task", {}) for rec in records for k in OUTCOME_ARRAYS):
        return None
    cols: dict[str, list] = {}
    for rec in records:
        pt = rec.get("per_task", {})
        for k in ("SR", *OUTCOME_ARRAYS):
            if k not in pt:
                raise PlateauError(f"validation record: per_task lacks {k!r}")
            cols.setdefault(k, []).append(np.asarray(pt[k], float).ravel())
    if not cols:
        raise PlateauError("validation record: no per-task records")
    c = {k: np.concatenate(v) for k, v in cols.items()}
    hit = c["contact_step"] >= 0
    person = c["contact_person"] > 0
    after = c["reached_after_contact"] > 0
    classes = {
        "goal": c["SR"] > 0,
        "person_then_goal": hit & person & after,
        "person": hit & person & ~after,
        "table_then_goal": hit & ~person & after,
        "table": hit & ~person & ~after,
        "timeout": ~hit & (c["SR"] == 0),
    }
    out: dict[str, Any] = {"episodes": int(c["SR"].size)}
    for k, m in classes.items():
        out[k] = int(m.sum())
        out[f"MGD_{k}"] = float(c["MGD"][m].mean()) if m.any() else None
    first = c["contact_step"][hit]
    out["median_first_contact_step"] = float(np.median(first)) if first.size else None
    return out


def run_summary(folder: Path) -> dict[str, Any]:
    """Every statistic of one run (see the module docstring)."""
    cfg = read_json(folder / "config.json")
    train = cfg.get("train", {})
    try:
        rpi = int(train["tasks_per_iteration"]) * int(train["posterior_episodes"])
        upi = int(train["updates_per_iteration"])
    except (KeyError, TypeError, ValueError):
        raise PlateauError(
            f"{folder / 'config.json'}: train.tasks_per_iteration, train.posterior_episodes and "
            "train.updates_per_iteration are needed"
        ) from None
    rows = read_metrics(folder / "metrics.jsonl")
    lift = liftoff(rows)
    last = rows[-1]["iteration"]
    before = [r for r in rows if lift is None or r["iteration"] < lift]
    after = [r for r in rows if lift is not None and r["iteration"] >= lift]
    near_before = [r for r in before if lift is not None and r["iteration"] >= lift - WINDOW]
    near_after = [r for r in after if r["iteration"] < lift + WINDOW] if lift else []
    at_lift = {r["iteration"]: r for r in rows}.get(lift, {})
    evals = [
        {
            k: r[k]
            for k in ("iteration", "test_SR", "test_CFR", "test_MGD", "val_SR", "val_CFR")
            if k in r
        }
        for r in rows
        if "test_SR" in r
    ]
    out: dict[str, Any] = {
        "folder": str(folder),
        "seed": cfg.get("seed"),
        "iterations": last,
        "rows_per_iteration": rpi,
        "updates_per_iteration": upi,
        "liftoff_iteration": lift,
        "liftoff_grad_steps": lift * upi if lift else None,
        "successes_from_start": row_counts(rows, rpi)["task_start_success"],
        "iterations_with_success": int(sum((r.get("train_success") or 0) > 0 for r in rows)),
        "before": {**window_means(before), "rows": row_counts(before, rpi)},
        "after": {**window_means(after), "rows": row_counts(after, rpi)} if after else None,
        "window_before": window_means(near_before) if near_before else None,
        "window_after": window_means(near_after) if near_after else None,
        "q_turn": q_turn(rows),
        "guide": guide_curriculum(rows, rpi, train.get("guide_steps")),
        "success_after_liftoff": [r.get("train_success") for r in after[:AFTER]],
        "at_liftoff": {k: at_lift.get(k) for k in ("alpha", "log_pi", "q_mean")} if lift else None,
        "mpc_reasons_before": mpc_reasons(before),
        "mpc_reasons_after": mpc_reasons(after),
        "early": early_features(rows, rpi),
        "evals": evals,
        "trajectory": {
            k: [None if not math.isfinite(v) else v for v in series(rows, k).tolist()]
            for k in (
                "q_mean",
                "log_pi",
                "alpha",
                "train_success",
                "train_explore_success",
                "train_guide_success",
                "train_collision_free",
                "train_mpc_share",
            )
            if any(k in r for r in rows)
        },
        "iteration": [r["iteration"] for r in rows],
    }
    val = folder / VAL8
    record = read_json(val) if val.is_file() else None
    out["val"] = val_outcomes(record) if record is not None else None
    if record is not None:
        out["val_SR"] = record["pooled"]["SR"]["mean"]
    return out


def seed_stats(values: Sequence[float | None]) -> dict[str, Any] | None:
    """Mean +- standard error over seeds, min and max, over the seeds that have a value."""
    v = np.array([x for x in values if x is not None], float)
    if not v.size:
        return None
    se = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else None
    return {
        "n": int(v.size),
        "mean": float(v.mean()),
        "se": se,
        "min": float(v.min()),
        "max": float(v.max()),
    }


def _ranks(x: np.ndarray) -> np.ndarray:
    """Average ranks (ties share their mean rank)."""
    order = np.argsort(x, kind="stable")
    r = np.empty(x.size)
    r[order] = np.arange(x.size, dtype=float)
    for u in np.unique(x):
        m = x == u
        r[m] = r[m].mean()
    return r


def spearman(
    x: Sequence[float],
    y: Sequence[float],
    strata: Sequence[str] | None = None,
    reps: int = 20000,
    seed: int = 0,
) -> dict[str, Any] | None:
    """Spearman's rank correlation with a two-sided permutation p-value (y permuted within each
    stratum when strata are given, so that pooled arms are only compared with themselves:
    each arm's values are ranked within the arm first)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    s = np.asarray(strata if strata is not None else ["all"] * x.size)[ok]
    x, y = x[ok], y[ok]
    if x.size < 4:
        return None
    rx, ry = np.empty(x.size), np.empty(x.size)
    for u in np.unique(s):
        m = s == u
        rx[m], ry[m] = _ranks(x[m]) / max(m.sum() - 1, 1), _ranks(y[m]) / max(m.sum() - 1, 1)

    def rho(a: np.ndarray, b: np.ndarray) -> float:
        a, b = a - a.mean(), b - b.mean()
        d = math.sqrt(float((a * a).sum() * (b * b).sum()))
        return float((a * b).sum() / d) if d > 0 else 0.0

    r0 = rho(rx, ry)
    rng = np.random.default_rng(seed)
    groups = [np.flatnonzero(s == u) for u in np.unique(s)]
    hits = 0
    for _ in range(reps):
        perm = np.arange(x.size)
        for g in groups:
            perm[g] = rng.permutation(g)
        hits += abs(rho(rx, ry[perm])) >= abs(r0) - 1e-12
    return {"n": int(x.size), "rho": r0, "p": (hits + 1) / (reps + 1)}


def correlations(runs: list[dict], strata: list[str] | None = None) -> dict[str, Any]:
    """Rank correlation of the lift-off iteration (a seed that never lifted off ranks after
    every seed that did) with each early feature."""
    lift = [r["liftoff_iteration"] or r["iterations"] + 1 for r in runs]
    return {
        f: spearman(
            [r["early"][f] if r["early"][f] is not None else np.nan for r in runs], lift, strata
        )
        for f in EARLY_FEATURES
    }


def prob_less(x: Sequence[float], y: Sequence[float], reps: int = 20000, seed: int = 0) -> dict:
    """P(a value of x is below a value of y) (ties half) over all pairs, with a two-sided
    permutation p-value for 0.5 (the two samples' labels shuffled)."""
    x, y = np.asarray(x, float), np.asarray(y, float)

    def prob(u: np.ndarray, v: np.ndarray) -> float:
        d = u[:, None] - v[None, :]
        return float(((d < 0) + 0.5 * (d == 0)).mean())

    p0 = prob(x, y)
    both = np.concatenate([x, y])
    rng = np.random.default_rng(seed)
    hits = 0
    for _ in range(reps):
        q = rng.permutation(both)
        hits += abs(prob(q[: x.size], q[x.size :]) - 0.5) >= abs(p0 - 0.5) - 1e-12
    return {"n": [int(x.size), int(y.size)], "p_less": p0, "p": (hits + 1) / (reps + 1)}


def liftoff_steps(r: dict) -> float:
    """Gradient steps to the first success; a seed that never lifted off counts after its
    budget."""
    lift = r["liftoff_iteration"]
    return (lift if lift else r["iterations"] + 1) * r["updates_per_iteration"]


def window_success(r: dict, first: int, last: int) -> float | None:
    """Mean success from the task's start over iterations first..last (None if the run did not
    reach `last`)."""
    if r["iterations"] < last:
        return None
    it = np.array(r["iteration"])
    y = np.array([np.nan if v is None else v for v in r["trajectory"]["train_success"]], float)
    return _mean(y[(it >= first) & (it <= last)])


SUCCESS_WINDOWS = ((1, 20), (21, 40), (41, 60), (56, 75), (76, 95))


def _guide_group(gs: list[dict]) -> dict[str, Any] | None:
    if not gs:
        return None
    return {
        "guided_rows_per_iteration": seed_stats([g["guided_rows_per_iteration"] for g in gs]),
        "h_at_10": seed_stats([g["h_at"][10] for g in gs]),
        "h_at_25": seed_stats([g["h_at"][25] for g in gs]),
        "shrinks": seed_stats([g["shrinks"] for g in gs]),
        "rows_behind_a_shrink": seed_stats(
            [g["rows_behind_a_shrink"]["mean"] for g in gs if g["rows_behind_a_shrink"]]
        ),
        "guide_success_1_10": seed_stats([g["guide_success_1_10"] for g in gs]),
        "guide_success_11_30": seed_stats([g["guide_success_11_30"] for g in gs]),
    }


def group_summary(runs: list[dict]) -> dict[str, Any]:
    lifted = [r for r in runs if r["liftoff_iteration"] is not None]
    pick = lambda side, k: [(r[side] or {}).get(k) for r in runs]  # noqa: E731
    return {
        "seeds": len(runs),
        "lifted_off": len(lifted),
        "liftoff_iteration": seed_stats([r["liftoff_iteration"] for r in lifted]),
        "val_SR": seed_stats([r.get("val_SR") for r in runs]),
        "early": {f: seed_stats([r["early"][f] for r in runs]) for f in EARLY_FEATURES},
        "before": {
            k: seed_stats(pick("before", k)) for k in FIELDS if any(k in r["before"] for r in runs)
        },
        "after": {
            k: seed_stats(pick("after", k))
            for k in FIELDS
            if any(k in (r["after"] or {}) for r in runs)
        },
        "window_before": {k: seed_stats(pick("window_before", k)) for k in FIELDS},
        "window_after": {k: seed_stats(pick("window_after", k)) for k in FIELDS},
        **{
            f"success_after_{k}": seed_stats(
                [
                    float(np.mean(r["success_after_liftoff"][:k]))
                    for r in lifted
                    if len(r["success_after_liftoff"]) >= k
                ]
            )
            for k in (10, 20, 30)
        },
        "guide": _guide_group([r["guide"] for r in runs if r.get("guide")]),
        "q_min_iteration": seed_stats([r["q_turn"].get("min_iteration") for r in runs]),
        "q_last_minus_min": seed_stats(
            [r["q_turn"]["last"] - r["q_turn"]["min"] for r in runs if r["q_turn"]]
        ),
        "task_start_episodes_before": seed_stats([r["before"]["rows"]["task_start"] for r in runs]),
        "explore_successes_before": seed_stats(
            [r["before"]["rows"]["explore_success"] for r in runs]
        ),
    }


# ---- figures -------------------------------------------------------------------------------

_COLORS = {"early": "tab:green", "late": "tab:orange", "never": "tab:red"}


def _kind(run: dict, split: int) -> str:
    lift = run["liftoff_iteration"]
    return "never" if lift is None else ("early" if lift <= split else "late")


def _smooth(y: Sequence[float | None], k: int = 5) -> np.ndarray:
    y = np.array([np.nan if v is None else v for v in y], float)
    out = np.full(y.size, np.nan)
    for i in range(y.size):
        w = y[max(0, i - k + 1) : i + 1]
        w = w[np.isfinite(w)]
        out[i] = w.mean() if w.size else np.nan
    return out


def figure_trajectories(groups: dict[str, list[dict]], path: Path, split: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [
        ("q_mean", "mean Q"),
        ("log_pi", "log pi (target 2)"),
        ("alpha", "alpha (log)"),
        ("train_explore_success", "exploring-start success (5-it mean)"),
    ]
    fig, axes = plt.subplots(len(keys), 2, figsize=(11, 11), sharex="col")
    for col, name in enumerate(("default", "recipe")):
        for run in groups.get(name, []):
            c = _COLORS[_kind(run, split)]
            it = np.array(run["iteration"])
            for row, (k, _) in enumerate(keys):
                y = run["trajectory"].get(k)
                if y is None:
                    continue
                y = _smooth(y) if k.startswith("train_") else np.array(y, float)
                ax = axes[row, col]
                ax.plot(it, y, color=c, lw=1, alpha=0.8)
                if run["liftoff_iteration"]:
                    j = run["liftoff_iteration"] - it[0]
                    ax.plot(it[j], y[j], "o", color=c, ms=4)
        for row, (_, label) in enumerate(keys):
            axes[row, col].set_ylabel(label)
        axes[2, col].set_yscale("log")
        axes[0, col].set_title(
            f"{name}: {len(groups.get(name, []))} seeds (dot: first success from the start)"
        )
        axes[-1, col].set_xlabel("iteration (500 gradient steps each)")
    handles = [plt.Line2D([], [], color=c, label=k) for k, c in _COLORS.items()]
    fig.legend(
        handles=handles, title=f"first success (early: <= it {split})", loc="lower center", ncol=3
    )
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_rows(groups: dict[str, list[dict]], path: Path) -> None:
    """Success of the posterior-phase episodes by start, mean over seeds per iteration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in ("default", "recipe", "guide") if n in groups]
    fig, axes = plt.subplots(1, len(names), figsize=(5 * len(names), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    labels = {
        "train_success": "task's start",
        "train_explore_success": "exploring start",
        "train_guide_success": "MPC roll-in, then the policy",
    }
    for ax, name in zip(axes, names, strict=True):
        runs = groups[name]
        n = min(len(r["iteration"]) for r in runs)
        for k, label in labels.items():
            ys = [r["trajectory"][k][:n] for r in runs if k in r["trajectory"]]
            if not ys:
                continue
            y = np.nanmean(np.array(ys, dtype=float), axis=0)
            ax.plot(np.arange(1, n + 1), _smooth(list(y)), label=label)
        ax.set_title(f"{name} ({len(runs)} seeds)")
        ax.set_xlabel("iteration")
    axes[0].set_ylabel("success, mean over seeds (5-it mean)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_after(groups: dict[str, list[dict]], path: Path) -> None:
    """Success from the task's start in the iterations from the first success on, per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in ("default", "recipe") if n in groups]
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    for ax, name in zip(axes, names, strict=True):
        for r in groups[name]:
            y = r["success_after_liftoff"]
            if not y:
                continue
            lab = f"s{r['seed']} (it {r['liftoff_iteration']})"
            ax.plot(np.arange(len(y)), _smooth(y), lw=1, label=lab)
        ax.set_title(f"{name}: seeds that lifted off")
        ax.set_xlabel("iterations since the first success from the start")
        ax.legend(fontsize=7, ncol=2)
    axes[0].set_ylabel("success from the start (5-it mean)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_outcomes(groups: dict[str, list[dict]], path: Path) -> None:
    """How the final policy's 192 validation episodes ended, per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cats = [
        ("goal", "goal", "tab:green"),
        ("person_then_goal", "person, then goal", "yellowgreen"),
        ("person", "person", "tab:red"),
        ("table_then_goal", "table, then goal", "khaki"),
        ("table", "table", "tab:brown"),
        ("timeout", "out of time", "tab:gray"),
    ]
    bars = [(f"{g} s{r['seed']}", r) for g in ("default", "recipe") for r in groups.get(g, [])]
    bars = [(lab, r) for lab, r in bars if r["val"] is not None]
    fig, ax = plt.subplots(figsize=(12, 4))
    bottom = np.zeros(len(bars))
    for key, label, color in cats:
        v = np.array([r["val"][key] / r["val"]["episodes"] for _, r in bars])
        ax.bar(range(len(bars)), v, bottom=bottom, color=color, label=label)
        bottom += v
    ax.set_xticks(range(len(bars)), [lab for lab, _ in bars], rotation=60, ha="right")
    ax.set_ylabel("share of 192 validation episodes")
    ax.legend(ncol=6, fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_early(groups: dict[str, list[dict]], path: Path) -> None:
    """Lift-off iteration against four statistics of iterations 1-20, all 75-iteration runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    feats = [
        ("q_mean_at_20", "mean Q at iteration 20"),
        ("alpha_min", "lowest alpha (log scale)"),
        ("alpha_min_iteration", "iteration of the lowest alpha"),
        ("explore_success_1_20", "exploring-start success, it 1-20"),
        ("collision_free_1_20", "collision-free from the start, it 1-20"),
    ]
    fig, axes = plt.subplots(1, len(feats), figsize=(19, 3.8), sharey=True)
    marks = {"default": ("o", "k")} | {
        a: ("x", c)
        for a, c in zip(
            SCREEN_ARMS,
            ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown"),
            strict=True,
        )
    }
    for ax, (f, label) in zip(axes, feats, strict=True):
        for name, (m, c) in marks.items():
            runs = groups.get(name, [])
            x = [r["early"][f] for r in runs]
            y = [r["liftoff_iteration"] or r["iterations"] + 3 for r in runs]
            ax.scatter(x, y, marker=m, color=c, s=22, label=name)
        ax.axhline(76, color="gray", lw=0.5)
        ax.set_xlabel(label)
        if f == "alpha_min":
            ax.set_xscale("log")
    axes[0].set_ylabel("first success (iteration; 78: never)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- command line ----------------------------------------------------------------------------


def analyse(root: Path, groups: dict[str, list[str]] | None = None) -> dict[str, Any]:
    groups = GROUPS if groups is None else groups
    runs = {g: [run_summary(root / f) for f in folders] for g, folders in groups.items()}
    report: dict[str, Any] = {
        "early_iterations": EARLY,
        "window": WINDOW,
        "groups": {g: group_summary(rs) for g, rs in runs.items()},
        "correlations": {},
        "runs": runs,
    }
    if "default" in runs:
        report["correlations"]["default"] = correlations(runs["default"])
    pooled = [g for g in ("default", *SCREEN_ARMS) if g in runs]
    if len(pooled) > 1:
        rs = [r for g in pooled for r in runs[g]]
        strata = [g for g in pooled for _ in runs[g]]
        report["correlations"]["screen_pooled_by_arm"] = correlations(rs, strata)
        # the runs whose alpha reached its lowest point before their first success, so that the
        # whole-run alpha minimum is a statistic of the time before lift-off
        keep = [
            i
            for i, r in enumerate(rs)
            if r["liftoff_iteration"] is None
            or r["early"]["alpha_min_iteration"] < r["liftoff_iteration"]
        ]
        report["correlations"]["screen_pooled_by_arm_alpha_min_first"] = correlations(
            [rs[i] for i in keep], [strata[i] for i in keep]
        )
    if "recipe" in runs and "default" in runs:
        report["recipe_earlier_than_default"] = prob_less(
            [liftoff_steps(r) for r in runs["recipe"]], [liftoff_steps(r) for r in runs["default"]]
        )
    # success from the task's start in 20-iteration windows (10,000 gradient steps), per group,
    # and P(a default seed is below a recipe seed) per window
    report["success_windows"] = {
        g: {
            f"{a}-{b}": seed_stats([window_success(r, a, b) for r in rs])
            for a, b in SUCCESS_WINDOWS
        }
        for g, rs in runs.items()
    }
    base = "default_it95" if "default_it95" in runs else "default"
    if "recipe" in runs and base in runs:
        cmp = {}
        for a, b in SUCCESS_WINDOWS:
            x = [window_success(r, a, b) for r in runs[base]]
            y = [window_success(r, a, b) for r in runs["recipe"]]
            x, y = [v for v in x if v is not None], [v for v in y if v is not None]
            if len(x) > 1 and len(y) > 1:
                cmp[f"{a}-{b}"] = prob_less(x, y)
        report["success_windows_default_below_recipe"] = {"baseline": base, **cmp}
    return report


def _rounded(x: Any) -> Any:
    """Floats to 4 significant digits, for a readable summary file."""
    if isinstance(x, float):
        return float(f"{x:.4g}") if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_rounded(v) for v in x]
    return x


def write(report: dict[str, Any], out: Path, split: int = 50) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    runs = report["runs"]
    files = [out / "summary.json"]
    slim = {
        **report,
        "runs": {
            g: [{k: v for k, v in r.items() if k not in ("trajectory", "iteration")} for r in rs]
            for g, rs in runs.items()
        },
    }
    files[0].write_text(json.dumps(_rounded(slim), indent=1) + "\n")
    # outcomes.png only where a `default` or `recipe` run's validation outcomes are recorded
    outcomes = any(r["val"] is not None for g in ("default", "recipe") for r in runs.get(g, []))
    for name, fn in (
        ("trajectories.png", lambda p: figure_trajectories(runs, p, split)),
        ("rows.png", lambda p: figure_rows(runs, p)),
        ("after-liftoff.png", lambda p: figure_after(runs, p)),
        ("outcomes.png", lambda p: figure_outcomes(runs, p)),
        ("early-vs-liftoff.png", lambda p: figure_early(runs, p)),
    ):
        if name == "outcomes.png" and not outcomes:
            continue
        fn(out / name)
        files.append(out / name)
    return files


def _fmt(s: dict | None, d: int = 2) -> str:
    if s is None:
        return "-"
    se = f" +- {s['se']:.{d}f}" if s["se"] is not None else ""
    return f"{s['mean']:.{d}f}{se} [{s['min']:.{d}f}, {s['max']:.{d}f}]"


def print_summary(report: dict[str, Any]) -> None:
    for g, s in report["groups"].items():
        print(
            f"{g}: lifted off {s['lifted_off']}/{s['seeds']}, first success "
            f"{_fmt(s['liftoff_iteration'], 1)}, val SR {_fmt(s['val_SR'])}"
        )
    for g, rs in report["runs"].items():
        for r in rs:
            v = r["val"] or {}
            print(
                f"  {g} s{r['seed']}: lift {r['liftoff_iteration']}, successes "
                f"{r['successes_from_start']}, before: {r['before']['rows']}, val "
                f"{ {k: v.get(k) for k in ('goal', 'person', 'table', 'timeout')} }"
            )
    for k in ("recipe_earlier_than_default", "success_windows_default_below_recipe"):
        if k in report:
            print(k, report[k])
    for g, w in report["success_windows"].items():
        print(g, {k: _fmt(v) for k, v in w.items()})
    for scope, cs in report["correlations"].items():
        print(scope)
        for f, c in cs.items():
            if c:
                print(f"  {f:24s} rho {c['rho']:+.2f}  p {c['p']:.3f}  n {c['n']}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m lab.diagnostics.plateau", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--root", type=Path, default=Path("."), help="the repository root")
    p.add_argument("--out", type=Path, default=OUT, help=f"output folder (default {OUT})")
    p.add_argument("--quiet", action="store_true", help="no summary on stdout")
    args = p.parse_args(argv)
    try:
        report = analyse(args.root)
    except PlateauError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    files = write(report, args.out)
    if not args.quiet:
        print_summary(report)
    print("wrote " + ", ".join(str(f) for f in files))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
