"""Values from the committed records and their statistics: `Records` reads each record once and
names the missing ones; `run_value`/`entry_values` give one cell's per-seed values; seed
statistics, paired differences over tasks and over seeds, and the verdict on an ordering."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scipy.stats import t as student_t

from lab.tables.catalogue import Entry
from mpcpearl_jax.evaluation import metrics
from mpcpearl_jax.evaluation.report import PAPER

VAL8 = "eval/policy-val-seeds1-8/results.json"  # 192 validation tasks (task seeds 1-8), pooled
SCENARIOS = {  # the paper's 25 test and 25 OOD scenarios
    "scen_test": "eval/policy-scenarios-test/results.json",
    "scen_ood": "eval/policy-scenarios-ood/results.json",
}
RESULTS_KEY = {"test": "test_adapt", "online": "test_online", "ood": "ood_adapt"}
# the worst seed of these is the largest value: the metrics lower is better of (method §8,
# `evaluation.metrics.METRICS`) and the minutes to a first success
LOWER_IS_BETTER = metrics.LOWER_IS_BETTER | {"first_success_min"}
NO_RECORD = "-"  # a record that does not exist by design (e.g. no validation run)
MISSING = "MISSING"  # a record that should exist and does not (reported, never filled in)


@dataclass(frozen=True)
class Stat:
    """One seed's value; se is the standard error over tasks where the record gives one."""

    value: float
    se: float | None = None


@dataclass
class Records:
    """Reads records under `results`, once each; remembers the ones that should exist and do
    not (`missing`, paths as given to `read`)."""

    results: Path
    missing: list[str] = field(default_factory=list)
    _cache: dict[Path, Any] = field(default_factory=dict)

    def read(self, rel: str) -> Any:
        """The parsed record (a list of rows for .jsonl), or None if the file is absent."""
        path = self.results / rel
        if path not in self._cache:
            if not path.is_file():
                self._cache[path] = None
            elif path.suffix == ".jsonl":
                lines = path.read_text().splitlines()
                self._cache[path] = [json.loads(line) for line in lines if line.strip()]
            else:
                self._cache[path] = json.loads(path.read_text())
        if self._cache[path] is None:
            shown = str(Path(self.results.name) / rel)
            if shown not in self.missing:
                self.missing.append(shown)
        return self._cache[path]


# ---------------------------------------------------------------- values from records


def run_value(rec: Records, run: str, kind: str, metric: str) -> Stat | None:
    """One run folder's value of `metric` for `kind`, or None (and noted) if the record is
    missing."""
    if kind in RESULTS_KEY:
        res = rec.read(f"{run}/results.json")
        return None if res is None else Stat(res[RESULTS_KEY[kind]][metric])
    if kind == "val8":
        return pooled_value(rec, f"{run}/{VAL8}", metric)
    if kind in SCENARIOS:
        res = rec.read(f"{run}/{SCENARIOS[kind]}")
        return None if res is None else Stat(res["metrics"][metric])
    if kind in ("budget", "grad_steps", "val_end"):
        return _curve_value(rec, run, kind, metric)
    raise ValueError(f"unknown kind {kind!r}")


def pooled_value(rec: Records, rel: str, metric: str) -> Stat | None:
    res = rec.read(rel)
    if res is None:
        return None
    p = res["pooled"][metric]
    return Stat(p["mean"], p["se"])


def _curve_value(rec: Records, run: str, kind: str, metric: str) -> Stat | None:
    """experiments.learning's curve.json; a run of the training CLIs has none: its budget is the
    training wall time of metrics.jsonl and its gradient steps iterations x updates."""
    if (rec.results / run / "curve.json").is_file():
        curve = rec.read(f"{run}/curve.json")
        if kind == "budget":
            return Stat(curve["budget_minutes"])
        if kind == "grad_steps":
            return Stat(curve["grad_steps"])
        return Stat(curve["points"][-1][f"val_{metric}"])
    rows = rec.read(f"{run}/metrics.jsonl")
    cfg = rec.read(f"{run}/config.json")
    if rows is None or cfg is None or kind == "val_end":
        return None
    last = rows[-1]
    if kind == "budget":
        return Stat(lifetime_wall_s(rows) / 60)
    section = cfg.get("train", cfg.get("grbal"))
    return Stat(last["iteration"] * section["updates_per_iteration"])


def cumulative_wall_s(rows: list[dict]) -> list[float]:
    """Each metrics.jsonl row's wall seconds since the run started (a row without `wall_s` keeps
    the previous value). In records written before resumed runs carried their clocks on, the
    resumed process restarted `wall_s` at 0; each such drop closes a segment, and the segments
    add up."""
    out, total, prev = [], 0.0, 0.0
    for r in rows:
        wall = float(r.get("wall_s", prev))
        if wall < prev:
            total += prev
        prev = wall
        out.append(total + wall)
    return out


def lifetime_wall_s(rows: list[dict]) -> float:
    """A training CLI run's wall seconds over its lifetime from its metrics.jsonl rows
    (`cumulative_wall_s` of its last row)."""
    walls = cumulative_wall_s(rows)
    return walls[-1] if walls else 0.0


def entry_values(rec: Records, e: Entry, kind: str, metric: str) -> list[Stat] | str:
    """The per-seed values of one cell, or the text to show instead ('-' by design, MISSING)."""
    if kind in e.absent:
        return NO_RECORD
    if e.paper is not None:
        paper = PAPER["restaurant"][e.paper]
        ok = kind in ("test", "scen_test") and metric in paper
        return [Stat(paper[metric])] if ok else NO_RECORD
    if e.files:
        rel = dict(e.files).get(kind)
        if rel is None:
            return NO_RECORD
        if kind == "val8":
            stat = pooled_value(rec, rel, metric)
        else:
            res = rec.read(rel)
            stat = None if res is None else Stat(res["metrics"][metric])
        return MISSING if stat is None else [stat]
    stats = [run_value(rec, run, kind, metric) for run in e.runs]
    found = [s for s in stats if s is not None]
    return found if len(found) == len(stats) else MISSING


# ---------------------------------------------------------------- seed groups and pairs


def signed(x: float) -> str:
    """A difference with its sign to two decimals; one that rounds to zero is '+0.00', not
    '-0.00'."""
    return f"{round(x, 2) or 0.0:+.2f}"


def seed_stats(values: Sequence[float], metric: str) -> tuple[float, float, float]:
    """Mean, standard error over seeds (ddof 1) and the worst seed (the largest TT or MGD, the
    smallest of the others) of one configuration's per-seed values."""
    n = len(values)
    if n < 2:
        raise ValueError("a seed group needs at least two seeds")
    mean = sum(values) / n
    var = sum((v - mean) ** 2 for v in values) / (n - 1)
    worst = max(values) if metric in LOWER_IS_BETTER else min(values)
    return mean, math.sqrt(var / n), worst


@dataclass(frozen=True)
class Paired:
    """A - B over the same tasks: mean, its standard error over tasks, and task counts."""

    mean: float
    se: float
    tasks: int
    both: int
    only_a: int
    only_b: int

    def __str__(self) -> str:
        return (
            f"{signed(self.mean)} +- {self.se:.2f} over {self.tasks} tasks "
            f"({self.both} solved by both, {self.only_a} only by A, {self.only_b} only by B)"
        )


def per_task_sr(record: dict) -> tuple[list[tuple], list[float]]:
    """(task seed, task) keys and the per-task SR (mean over the policy's seeds) of a pooled
    `--task-seeds` record."""
    keys: list[tuple] = []
    sr: list[float] = []
    for r in record["records"]:
        rows = r["per_task"]["SR"]
        for i, task in enumerate(r["tasks"]):
            keys.append((r["task_seed"], task))
            sr.append(sum(row[i] for row in rows) / len(rows))
    return keys, sr


def paired_difference(a: dict, b: dict) -> Paired:
    """Paired difference of the SR of two pooled records over the same tasks (ValueError if the
    records' task seeds or tasks differ)."""
    ka, sa = per_task_sr(a)
    kb, sb = per_task_sr(b)
    if ka != kb:
        raise ValueError("the two records are not on the same tasks (task seeds or tasks differ)")
    d = [x - y for x, y in zip(sa, sb, strict=True)]
    n = len(d)
    mean = sum(d) / n
    se = math.sqrt(sum((v - mean) ** 2 for v in d) / (n - 1) / n)
    both = sum(1 for x, y in zip(sa, sb, strict=True) if x == 1 and y == 1)
    only_a = sum(1 for x, y in zip(sa, sb, strict=True) if x == 1 and y < 1)
    only_b = sum(1 for x, y in zip(sa, sb, strict=True) if y == 1 and x < 1)
    return Paired(mean, se, n, both, only_a, only_b)


# ---------------------------------------------------------------- seeds as the unit


def seed_difference(a: Sequence[Stat], b: Sequence[Stat]) -> tuple[float, float, int] | None:
    """Mean and standard error over seeds of the per-seed difference A - B (seed i of A against
    seed i of B, over the seeds both have), and that number of seeds; None below two seeds."""
    d = [x.value - y.value for x, y in zip(a, b, strict=False)]
    n = len(d)
    if n < 2:
        return None
    mean = sum(d) / n
    return mean, math.sqrt(sum((v - mean) ** 2 for v in d) / (n - 1) / n), n


# seeds per method below which no verdict is given: with two, the t interval has one degree of
# freedom, and two seeds that happen to differ by the same amount (se 0) would read as 'holds'
MIN_VERDICT_SEEDS = 3


def verdict(diff: tuple[float, float, int] | None) -> str:
    """The paper's 'A > B' as measured: holds (the 95 % t interval over seeds lies above 0),
    does not hold (below 0, or B ahead), or cannot be told apart (it contains 0); no verdict
    below `MIN_VERDICT_SEEDS` seeds each."""
    if diff is None or diff[2] < MIN_VERDICT_SEEDS:
        return f"fewer than {MIN_VERDICT_SEEDS} seeds each: no verdict"
    mean, se, n = diff
    half = float(student_t.ppf(0.975, n - 1)) * se  # two-sided 95 %, seeds - 1 degrees of freedom
    if mean - half > 0:
        return "holds"
    if mean + half < 0:
        return "does not hold (B ahead)"
    return "cannot be told apart"


# ---------------------------------------------------------------- learning-curve points


def curve_point(rec: Records, run: str, minute: float) -> dict | None:
    """The evaluation point of a run's curve.json nearest `minute` (within half an evaluation
    interval), or None (noted as missing)."""
    curve = rec.read(f"{run}/curve.json")
    if curve is None:
        return None
    near = [
        p for p in curve["points"] if abs(p["minutes"] - minute) < curve["eval_every_minutes"] / 2
    ]
    if not near:
        rec.missing.append(f"{rec.results.name}/{run}/curve.json: no point at {minute:g} minutes")
        return None
    return near[0]


def curve_values(rec: Records, runs: Sequence[str], minute: float, key: str) -> list[Stat] | str:
    points = [curve_point(rec, run, minute) for run in runs]
    return MISSING if any(p is None for p in points) else [Stat(p[key]) for p in points]
