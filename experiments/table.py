"""The results tables of README.md and results/README.md, generated from the committed records.

    python -m experiments.table              # rewrite the tables between their marker comments
    python -m experiments.table --check      # exit 1 with a diff if the committed text differs
    python -m experiments.table --paired results/restaurant/pearl results/restaurant/mpc-sac

Every number comes from a record under results/: a run folder's `results.json` (test tasks after
two adaptation episodes, online, OOD), `curve.json` (budget, gradient steps, the last validation
point; `metrics.jsonl` and `config.json` where a run has no curve), its
`eval/policy-val-seeds1-8/results.json` (192 validation tasks, pooled) and
`eval/policy-scenarios-{test,ood}/results.json` (the paper's 25 test and 25 OOD scenarios); the
GP-MPC's from `results/gp_mpc/`; the paper's from `mpcpearl_jax.evaluation.report.PAPER`. A table
lists its
rows (or columns) in `README_QUALITY` and `RESTAURANT`: a label and one run folder, or several
folders of one configuration (one per seed), shown as mean +- standard error over the seeds and
the worst seed. A missing record is reported by name (exit 1), never filled in.

`--paired A B` prints the paired difference A - B of the success rate over the 192 validation
tasks (the same tasks for both: the same task seeds, in the same order), with its standard error
over tasks and how many tasks each solved alone.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import re
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mpcpearl_jax.evaluation.report import PAPER

VAL8 = "eval/policy-val-seeds1-8/results.json"  # 192 validation tasks (task seeds 1-8), pooled
SCENARIOS = {  # the paper's 25 test and 25 OOD scenarios
    "scen_test": "eval/policy-scenarios-test/results.json",
    "scen_ood": "eval/policy-scenarios-ood/results.json",
}
RESULTS_KEY = {"test": "test_adapt", "online": "test_online", "ood": "ood_adapt"}
# the worst seed of these is the largest value
LOWER_IS_BETTER = frozenset({"TT", "MGD", "first_success_min"})
NO_RECORD = "-"  # a record that does not exist by design (e.g. no validation run)
MISSING = "MISSING"  # a record that should exist and does not (reported, never filled in)


@dataclass(frozen=True)
class Entry:
    """One row (or column) of a table.

    runs: run folders under results/, one per seed of the same configuration; files: for a
    controller without a run folder (the GP-MPC), kind -> record file under results/; paper: a
    method of `PAPER["restaurant"]`; absent: kinds that have no record by design, shown as '-'.
    Kinds: test, online, ood (results.json), budget, grad_steps, val_end (curve.json), val8,
    scen_test, scen_ood (eval records).
    """

    label: str
    runs: tuple[str, ...] = ()
    files: tuple[tuple[str, str], ...] = ()
    paper: str | None = None
    absent: frozenset[str] = frozenset()

    def sources(self) -> list[str]:
        return list(self.runs) + [f for _, f in self.files]


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
        return _pooled(rec, f"{run}/{VAL8}", metric)
    if kind in SCENARIOS:
        res = rec.read(f"{run}/{SCENARIOS[kind]}")
        return None if res is None else Stat(res["metrics"][metric])
    if kind in ("budget", "grad_steps", "val_end"):
        return _curve_value(rec, run, kind, metric)
    raise ValueError(f"unknown kind {kind!r}")


def _pooled(rec: Records, rel: str, metric: str) -> Stat | None:
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


def lifetime_wall_s(rows: list[dict]) -> float:
    """A training CLI run's wall seconds over its lifetime from its metrics.jsonl rows. In records
    written before resumed runs carried their clocks on, the resumed process restarted `wall_s`
    at 0; each such drop closes a segment, and the segments add up."""
    total = prev = 0.0
    for r in rows:
        if "wall_s" not in r:
            continue
        if r["wall_s"] < prev:
            total += prev
        prev = r["wall_s"]
    return total + prev


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
            stat = _pooled(rec, rel, metric)
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


# ---------------------------------------------------------------- cells


def f2(x: float) -> str:
    return f"{x:.2f}"


def fmt_metric(stats: list[Stat] | str, metric: str, with_se: bool = False) -> str:
    """One metric: a single seed as the record has it (2 decimals, '+- se' over tasks where
    asked), a seed group as 'mean +- se (worst w)' over seeds."""
    if isinstance(stats, str):
        return stats
    if len(stats) == 1:
        s = stats[0]
        return f2(s.value) + (f" +- {f2(s.se)}" if with_se and s.se is not None else "")
    mean, se, worst = seed_stats([s.value for s in stats], metric)
    return f"{f2(mean)} +- {f2(se)} (worst {f2(worst)})"


def fmt_count(stats: list[Stat] | str, fmt: Callable[[float], str]) -> str:
    """Budget or gradient steps: one value, or the range over a group's seeds."""
    if isinstance(stats, str):
        return stats
    lo, hi = fmt(min(s.value for s in stats)), fmt(max(s.value for s in stats))
    return lo if lo == hi else f"{lo}-{hi}"


def _minutes(x: float) -> str:
    return f"{round(x, 1):g}"


def _steps(x: float) -> str:
    return str(int(round(x)))


def pair_cell(rec: Records, e: Entry, kind: str) -> str:
    """'SR / CFR' of one kind."""
    return " / ".join(fmt_metric(entry_values(rec, e, kind, m), m) for m in ("SR", "CFR"))


def val8_cell(rec: Records, e: Entry, cfr: bool) -> str:
    """SR on the 192 validation tasks (+- se over tasks for one seed, over seeds for a group),
    optionally with the CFR."""
    sr = fmt_metric(entry_values(rec, e, "val8", "SR"), "SR", with_se=True)
    if not cfr or sr == NO_RECORD:
        return sr
    c = entry_values(rec, e, "val8", "CFR")
    if isinstance(c, str):
        return f"{sr} (CFR {c})"
    return f"{sr} (CFR {f2(sum(s.value for s in c) / len(c))})"


def run_ref(e: Entry) -> str:
    return ", ".join(f"`{s}`" for s in e.sources())


# ---------------------------------------------------------------- the tables

METRICS = ("SR", "TT", "CFR", "SPL", "MGD")
SEEDS_NOTE = (
    "a +- b: the standard error over the 192 validation tasks for one seed; for a group of "
    "seeds, mean +- standard error over the seeds, then the worst seed."
)

_GP_MPC = Entry(
    "GP-MPC (this project)",
    files=(
        ("test", "gp_mpc/restaurant_test.json"),
        ("val8", "gp_mpc/restaurant_val_seeds1-8.json"),
        ("scen_test", "gp_mpc/scenarios/restaurant_test.json"),
        ("scen_ood", "gp_mpc/scenarios/restaurant_ood.json"),
    ),
)
_GP_MPC_TEACHER = Entry(
    "GP-MPC with unsafe-plan recovery (the learned agents' MPC)",
    files=(
        ("test", "gp_mpc/restaurant_test_unsafe-recovery.json"),
        ("val8", "gp_mpc/restaurant_val_seeds1-8_unsafe-recovery.json"),
    ),
)
_HEADLINE = "restaurant/mpc-pearl-eps0.2"
_NO_CURVE = frozenset({"val_end"})
_NO_VAL = frozenset({"val8"})
_NO_SCEN = frozenset({"scen_test", "scen_ood"})

# the five-seed comparison's MPC-PEARL 0.2 seeds finished so far (seeds 0, 1, ... in order)
CAMPAIGN_MPC_PEARL = (
    "restaurant/ablation/auto-entropy-24min",
    "restaurant/ablation/auto-entropy-seed1-24min",
    "restaurant/seeds/mpc-pearl-s2",
    "restaurant/seeds/mpc-pearl-s3",
    "restaurant/seeds/mpc-pearl-s4",
)
README_QUALITY: tuple[Entry, ...] = (
    _GP_MPC,
    Entry("MPC-PEARL 0.2 (`cpu-explore`), 60 min", (_HEADLINE,)),
    Entry("PEARL (`cpu-explore`), 60 min", ("restaurant/pearl",)),
    Entry("MPC-SAC 0.2 (`cpu-explore`), 60 min", ("restaurant/mpc-sac",)),
    Entry(
        "PEARL (`cpu-tuned`), 60 min, seeds 0 and 1",
        ("restaurant/ablation/pearl-tuned-60min", "restaurant/ablation/pearl-seed1-60min"),
    ),
    Entry(
        f"MPC-PEARL 0.2 (`cpu-auto`), 24 min, seeds 0-{len(CAMPAIGN_MPC_PEARL) - 1}",
        CAMPAIGN_MPC_PEARL,
    ),
    Entry("MPC-PEARL 0.2 ext. (`cpu-tuned`), 60 min", ("restaurant/ablation/extended-60min",)),
    Entry("MPC-SAC 0.2 ext. (`cpu-tuned`), 60 min", ("restaurant/ablation/mpc-sac-tuned-60min",)),
    Entry("MPC-PEARL 0.2 paper alg. (`cpu-paper`), 60 min", ("restaurant/mpc-pearl-eps0.2-paper",)),
    Entry(
        "GrBAL, 16 min beside other jobs, paper's observation",
        ("restaurant/grbal",),
        absent=_NO_VAL | _NO_SCEN,
    ),
    Entry("main command (`default`), 5 min", ("restaurant/main-default",)),
    Entry("paper MPC-PEARL 0.2", paper="MPC-PEARL 0.2"),
    Entry("paper PEARL", paper="PEARL"),
    Entry("paper MPC-SAC", paper="MPC-SAC"),
)


def render_quality(rec: Records, entries: Sequence[Entry] = README_QUALITY) -> str:
    """README's table: one column per entry, one row per metric."""

    def metric_row(m: str) -> Callable[[Entry], str]:
        return lambda e: fmt_metric(entry_values(rec, e, "test", m), m)

    rows: list[tuple[str, Callable[[Entry], str]]] = [(m, metric_row(m)) for m in METRICS]
    rows += [
        ("val SR, 192 tasks", lambda e: val8_cell(rec, e, cfr=False)),
        ("SR / CFR, paper's 25 test scenarios", lambda e: pair_cell(rec, e, "scen_test")),
        ("SR / CFR, paper's 25 OOD scenarios", lambda e: pair_cell(rec, e, "scen_ood")),
    ]
    lines = [
        "| metric | " + " | ".join(e.label for e in entries) + " |",
        "|---|" + "---|" * len(entries),
    ]
    lines += [f"| {name} | " + " | ".join(f(e) for e in entries) + " |" for name, f in rows]
    notes = [
        "",
        "SR ... MGD: the 24 test tasks after two adaptation episodes; val SR: the 192 validation "
        "tasks; the scenario rows: the paper's own 25 test and 25 OOD crowds (`--scenarios`). "
        "Paper columns: the paper's table, measured on its 25 test scenarios "
        "(`mpcpearl_jax.evaluation.report.PAPER`). "
        + SEEDS_NOTE
        + " Records, under `results/`: "
        + "; ".join(f"{e.label}: {run_ref(e)}" for e in entries if e.sources())
        + ".",
    ]
    return "\n".join(lines + notes)


def _r(label: str, *runs: str, absent: frozenset[str] = frozenset()) -> Entry:
    return Entry(label, tuple(f"restaurant/{r}" for r in runs), absent=absent)


RESTAURANT: tuple[Entry, ...] = (
    _r(
        "MPC-PEARL 0.2, the headline (`cpu-explore`): the paper's event-triggered infusion on "
        "PEARL's configuration + exploring starts on half the posterior-phase episodes; seed 0",
        "mpc-pearl-eps0.2",
    ),
    _r("PEARL (eps 0), the headline's preset (`cpu-explore --eps 0`); seed 0", "pearl"),
    _r(
        "MPC-SAC 0.2, the headline's preset (`cpu-explore --algo sac --eps 0.2`: no encoder); "
        "seed 0",
        "mpc-sac",
    ),
    _r(
        "PEARL (eps 0), `cpu-tuned` (the MPC-based options are inactive without MPC); seed 0",
        "ablation/pearl-tuned-60min",
    ),
    _r("PEARL (eps 0), `cpu-tuned`, seed 1", "ablation/pearl-seed1-60min"),
    _r("PEARL (eps 0), `cpu-tuned`, seed 1, 25 minutes", "ablation/pearl-seed1-25min"),
    _r(
        "MPC-PEARL 0.2, the README's main command (`default`: `cpu-explore` with 2 x 64 "
        "networks, 4 tasks per step, automatic entropy tuning; 75 iterations)",
        "main-default",
        absent=_NO_CURVE,
    ),
    _r(
        "MPC-PEARL 0.2, `cpu-explore` + automatic entropy tuning "
        "(`--set pearl.auto_entropy=true`), 24 minutes, seed 0",
        "ablation/auto-entropy-24min",
    ),
    _r(
        "MPC-PEARL 0.2, `cpu-explore` + automatic entropy tuning, 24 minutes, seed 1",
        "ablation/auto-entropy-seed1-24min",
    ),
    _r(
        "PEARL (eps 0), `cpu-explore` + automatic entropy tuning, 24 minutes, seed 0",
        "ablation/pearl-auto-entropy-24min",
    ),
    _r(
        "MPC-SAC 0.2, `cpu-explore` + automatic entropy tuning, 24 minutes, seed 0",
        "ablation/mpc-sac-auto-entropy-24min",
    ),
    _r("MPC-PEARL 0.2, `cpu-explore`, seed 2, 20 minutes", "ablation/explore-starts-seed2-20min"),
    _r(
        "MPC-PEARL 0.2, `cpu-explore` + randomised crowd timing (`train.crowd_delay_max` 20), "
        "30 minutes, seed 0",
        "ablation/crowd-delay20-30min",
    ),
    _r(
        "MPC-PEARL 0.2, the paper's event-triggered infusion only on PEARL's configuration "
        "(`cpu-tuned` with warm start, MPC buffer and cloning off; no exploring starts), seed 0",
        "ablation/event-infusion-60min",
    ),
    _r(
        "MPC-PEARL 0.2, the same (event-triggered infusion only), seed 1",
        "ablation/event-infusion-seed1-60min",
    ),
    _r(
        "MPC-PEARL 0.2, the same (event-triggered infusion only), seed 2, 20 minutes",
        "ablation/event-infusion-seed2-20min",
    ),
    _r(
        "MPC-PEARL 0.2, extended (`cpu-tuned`: `cpu` + crowds re-drawn + velocity + sensing 3 m "
        "+ BC weight 4 + clock + egocentric + people nearest first), the previous headline",
        "ablation/extended-60min",
    ),
    _r("MPC-SAC 0.2, extended (`cpu-tuned`, no encoder)", "ablation/mpc-sac-tuned-60min"),
    _r(
        "MPC-PEARL 0.2, extended (`cpu-tuned`) with the MPC handed off early: warm start "
        "annealed to zero by iteration 60 instead of 400, cloning Q-filtered",
        "ablation/handoff-60min",
    ),
    _r(
        "MPC-PEARL 0.2, extended (`cpu-tuned`) + collision penalty 50 (`env.w_collision`)",
        "ablation/collision-penalty-60min",
    ),
    _r(
        "MPC-PEARL 0.2, extended (`cpu-tuned`) + DAgger labels (`train.mpc_dagger_labels`)",
        "ablation/dagger-labels-60min",
    ),
    _r(
        "MPC-PEARL 0.2, extended without the egocentric entries and the sorting (the clock run, "
        "an earlier headline)",
        "ablation/clock-60min",
    ),
    _r(
        "MPC-PEARL 0.2, the clock run's configuration + `pearl.policy_ema` 1e-4 (averaged "
        "policy deployed)",
        "ablation/policy-ema-60min",
    ),
    _r("MPC-SAC 0.2, the clock run's configuration (no encoder)", "ablation/mpc-sac-clock-60min"),
    _r(
        "MPC-PEARL 0.2, the clock run's configuration without the clock (the no-clock run)",
        "ablation/sensing-bc4-60min",
    ),
    _r(
        "PEARL (eps 0), the no-clock run's settings (MPC extensions inactive)",
        "ablation/pearl-sensing-60min",
    ),
    _r("MPC-SAC 0.2, the no-clock run's configuration (no encoder)", "ablation/mpc-sac-30min"),
    _r(
        "MPC-PEARL 0.2, paper's algorithm (`cpu-paper`: no extension, no observation option)",
        "mpc-pearl-eps0.2-paper",
    ),
    _r(
        "MPC-PEARL 0.2, re-drawn + velocity + sensing 3 m, BC weight 1",
        "ablation/redraw-sensing-24min",
    ),
    _r(
        "MPC-PEARL 0.2, extended (`cpu` + 40 behaviours + velocity)",
        "ablation/ext-40behaviours-25min",
    ),
    _r("MPC-PEARL 0.2, paper's algorithm (`cpu-paper`), first run", "ablation/paper-12min"),
    _r("PEARL (`cpu`, eps 0)", "ablation/pearl-10min"),
    _r("MPC-SAC 0.2 (`cpu`, no encoder)", "ablation/mpc-sac-10min"),
    _r(
        "MPC-PEARL 0.2, extended (`cpu`), val = train tasks",
        "ablation/cpu-30min",
        absent=_NO_VAL,
    ),
    _r("MPC-PEARL 0.2, extended (`cpu`) + mpc.r_safe 0.4", "ablation/cpu-rsafe0.4", absent=_NO_VAL),
    Entry(
        "GP-MPC, the paper's MPC at every step (no learning)",
        files=_GP_MPC.files,
    ),
    _GP_MPC_TEACHER,
    Entry("paper MPC-PEARL 0.2 (27 h on a GPU, 7 seeds)", paper="MPC-PEARL 0.2"),
    Entry("paper PEARL", paper="PEARL"),
    Entry("paper MPC-SAC", paper="MPC-SAC"),
    Entry("paper GP-MPC", paper="GP-MPC"),
)

_RESTAURANT_COLUMNS: tuple[tuple[str, Callable[[Records, Entry], str]], ...] = (
    ("budget (min)", lambda r, e: fmt_count(entry_values(r, e, "budget", ""), _minutes)),
    ("grad steps", lambda r, e: fmt_count(entry_values(r, e, "grad_steps", ""), _steps)),
    *(
        (m, lambda r, e, m=m: fmt_metric(entry_values(r, e, "test", m), m))
        for m in ("SR", "CFR", "TT", "SPL", "MGD")
    ),
    ("online SR / CFR", lambda r, e: pair_cell(r, e, "online")),
    ("OOD SR / CFR", lambda r, e: pair_cell(r, e, "ood")),
    ("val SR / CFR (end)", lambda r, e: pair_cell(r, e, "val_end")),
    ("val SR, 192 tasks (CFR)", lambda r, e: val8_cell(r, e, cfr=True)),
    ("25 test scenarios SR / CFR", lambda r, e: pair_cell(r, e, "scen_test")),
    ("25 OOD scenarios SR / CFR", lambda r, e: pair_cell(r, e, "scen_ood")),
)


def render_restaurant(rec: Records, entries: Sequence[Entry] = RESTAURANT) -> str:
    """results/README.md's table: one row per entry."""
    head = ["run"] + [name for name, _ in _RESTAURANT_COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for e in entries:
        label = f"{e.label} [{run_ref(e)}]" if e.sources() else e.label
        lines.append(
            "| " + " | ".join([label] + [f(rec, e) for _, f in _RESTAURANT_COLUMNS]) + " |"
        )
    notes = [
        "",
        "SR ... MGD: the 24 test tasks after two adaptation episodes; online: the same tasks with "
        "online adaptation; OOD: the 24 out-of-distribution tasks; val (end): the run's last "
        "validation point (24 tasks); the scenario columns: the paper's own 25 test and 25 OOD "
        "crowds (`--scenarios`). Paper rows: the paper's table "
        "(`mpcpearl_jax.evaluation.report.PAPER`), on "
        "its own 25 test scenarios. " + SEEDS_NOTE,
    ]
    return "\n".join(lines + notes)


# ---------------------------------------------------------------- blocks in the READMEs

# crowd perturbations (docs/method.md §8a) on the 192 validation tasks: folder suffix, label
PERTURBATIONS = (
    ("", "none"),
    ("-delay3", "delay 3"),
    ("-delay6", "delay 6"),
    ("-delay12", "delay 12"),
    ("-speed0.7", "speed 0.7"),
    ("-speed1.3", "speed 1.3"),
)
# the perturbations settings are chosen on (never the table's): `experiments.robustness
# --perturb delay=9 --perturb delay=15 --perturb speed=0.85 --perturb speed=1.15`
VALIDATION_PERTURBATIONS = (
    ("", "none"),
    ("-delay9", "delay 9"),
    ("-delay15", "delay 15"),
    ("-speed0.85", "speed 0.85"),
    ("-speed1.15", "speed 1.15"),
)
# the first rows of the robustness table; every other single-run entry of RESTAURANT with a
# 192-task validation record follows, then GP-MPC
ROBUSTNESS = (
    ("MPC-PEARL 0.2 (`cpu-explore`), 60 min", _HEADLINE),
    ("PEARL (`cpu-explore`), 60 min", "restaurant/pearl"),
    ("MPC-SAC 0.2 (`cpu-explore`), 60 min", "restaurant/mpc-sac"),
)
GP_MPC_ROW = "GP-MPC"


def _perturbed_record(run: str, suffix: str) -> str:
    if run == GP_MPC_ROW:
        if not suffix:  # the unperturbed GP-MPC record of the main table
            return "gp_mpc/restaurant_val_seeds1-8.json"
        return f"gp_mpc/perturbed/val{suffix}-seeds1-8/results.json"
    return f"{run}/eval/policy-val{suffix}-seeds1-8/results.json"


def robustness_rows(rec: Records) -> list[tuple[str, str]]:
    """The robustness table's rows: ROBUSTNESS, then every other single-run entry of the main
    table and GP-MPC once evaluated under the perturbations (`experiments.robustness`, whose
    last record, speed 1.3, marks it): from then on each of its cells must have a record."""
    rows, seen = list(ROBUSTNESS), {run for _, run in ROBUSTNESS}
    for label, run in [(e.label, e.runs[0]) for e in RESTAURANT if len(e.runs) == 1] + [
        (GP_MPC_ROW, GP_MPC_ROW)
    ]:
        if run not in seen and (rec.results / _perturbed_record(run, "-speed1.3")).is_file():
            rows.append((label, run))
            seen.add(run)
    return rows


def render_perturbed(
    rec: Records, rows: Sequence[tuple[str, str]], perturbations: Sequence[tuple[str, str]]
) -> list[str]:
    head = ["run", *(f"{label}" for _, label in perturbations)]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for label, run in rows:
        cells = []
        for suffix, _ in perturbations:
            rel = _perturbed_record(run, suffix)
            pair = [_pooled(rec, rel, m) for m in ("SR", "CFR")]
            cells.append(MISSING if None in pair else " / ".join(f2(p.value) for p in pair))
        ref = "" if run == GP_MPC_ROW else f" [`{run}`]"
        lines.append(f"| {label}{ref} | " + " | ".join(cells) + " |")
    return lines


def render_robustness(rec: Records, rows: Sequence[tuple[str, str]] | None = None) -> str:
    """SR / CFR of each run on the 192 validation tasks with the people's timing perturbed
    (`experiments.robustness`, i.e. `experiments.evaluate RUN --split val --task-seeds 1-8
    --perturb ...`)."""
    lines = render_perturbed(rec, robustness_rows(rec) if rows is None else rows, PERTURBATIONS)
    lines += [
        "",
        "SR / CFR on the 192 validation tasks (task seeds 1-8) with every person's timing "
        "perturbed on an unchanged path: delay K holds everyone at the start K more steps, speed "
        "S follows the paths S times as fast (docs/method.md §8a). Records: "
        "`RUN/eval/policy-val[-PERTURBATION]-seeds1-8/results.json`, GP-MPC's "
        "`gp_mpc/perturbed/`; produced by `python -m experiments.robustness --all --gp-mpc`.",
    ]
    return "\n".join(lines)


# the runs compared on the validation-only perturbations (the randomised crowd timing against
# the headline it modifies)
ROBUSTNESS_CHOICE = (
    ("MPC-PEARL 0.2 (`cpu-explore`), 60 min", _HEADLINE),
    (
        "MPC-PEARL 0.2, `cpu-explore` + randomised crowd timing (`train.crowd_delay_max` 20), "
        "30 min",
        "restaurant/ablation/crowd-delay20-30min",
    ),
)


def render_robustness_choice(rec: Records) -> str:
    """SR / CFR on the perturbations a training option is chosen on (never the table's)."""
    lines = render_perturbed(rec, ROBUSTNESS_CHOICE, VALIDATION_PERTURBATIONS)
    lines += [
        "",
        "SR / CFR on the 192 validation tasks (task seeds 1-8) under the perturbations used to "
        "choose a training option (delays 9 and 15, speeds 0.85 and 1.15), none of which is in "
        "the robustness table. Records: `RUN/eval/policy-val[-PERTURBATION]-seeds1-8/`.",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------- five seeds per method

# the five-seed comparison (`python -m experiments.campaign
# experiments/campaigns/restaurant-seeds.json`): method -> its seed folders (seeds 0, 1, ... in
# order), each trained alone for 24 minutes with `--preset cpu-auto`; a folder is listed once its
# campaign run and evaluations have finished. These methods are trained by the learning harness,
# so they also have the learning-curve table.
CURVE_SEED_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("MPC-PEARL 0.2", CAMPAIGN_MPC_PEARL),
    (
        "PEARL",
        (
            "restaurant/ablation/pearl-auto-entropy-24min",
            "restaurant/seeds/pearl-s1",
            "restaurant/seeds/pearl-s2",
            "restaurant/seeds/pearl-s3",
            "restaurant/seeds/pearl-s4",
        ),
    ),
    (
        "MPC-SAC 0.2",
        (
            "restaurant/ablation/mpc-sac-auto-entropy-24min",
            "restaurant/seeds/mpc-sac-s1",
            "restaurant/seeds/mpc-sac-s2",
            "restaurant/seeds/mpc-sac-s3",
            "restaurant/seeds/mpc-sac-s4",
        ),
    ),
)
# `experiments/campaigns/grbal-seeds.json`: `--preset cpu`, 24 minutes alone per seed; GrBAL's
# trainer writes no curve.json, so it is in the seed table only
SEED_GROUPS = (
    *CURVE_SEED_GROUPS,
    (
        "GrBAL",
        (
            "restaurant/seeds/grbal-s0",
            "restaurant/seeds/grbal-s1",
            "restaurant/seeds/grbal-s2",
            "restaurant/seeds/grbal-s3",
            "restaurant/seeds/grbal-s4",
        ),
    ),
)
# evaluation sets of the seed table: kind, label
SEED_SETS = (
    ("test", "24 test tasks"),
    ("val8", "192 validation tasks"),
    ("online", "24 test tasks, online"),
    ("ood", "24 OOD tasks"),
    ("scen_test", "paper's 25 test scenarios"),
    ("scen_ood", "paper's 25 OOD scenarios"),
)
# the paper's ordering claim, as pairs (A, B): A > B in the paper's table
PAPER_ORDER = (
    ("MPC-PEARL 0.2", "PEARL"),
    ("PEARL", "MPC-SAC 0.2"),
    ("MPC-PEARL 0.2", "MPC-SAC 0.2"),
    # section IV-A: "GrBAL presents the worst performance", "MPC-SAC shows slightly better results
    # compared to GrBAL"
    ("MPC-SAC 0.2", "GrBAL"),
    ("MPC-PEARL 0.2", "GrBAL"),
)
# two-sided 95 % Student t quantiles by degrees of freedom (seeds - 1)
T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447}


def seed_cell(stats: list[Stat] | str, metric: str) -> str:
    """'mean +- se (worst w)' over seeds; one seed alone is shown as its value '(1 seed)'."""
    if isinstance(stats, str):
        return stats
    if len(stats) == 1:
        return f"{f2(stats[0].value)} (1 seed)"
    return fmt_metric(stats, metric)


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
    half = T95.get(n - 1, 1.96) * se
    if mean - half > 0:
        return "holds"
    if mean + half < 0:
        return "does not hold (B ahead)"
    return "cannot be told apart"


def render_seeds(
    rec: Records,
    groups: Sequence[tuple[str, Sequence[str]]] = SEED_GROUPS,
    sets: Sequence[tuple[str, str]] = SEED_SETS,
    order: Sequence[tuple[str, str]] = PAPER_ORDER,
    claim: str = "paper's claim",
) -> str:
    """Per method and evaluation set: mean +- standard error over seeds and the worst seed of
    SR, CFR, TT, SPL and MGD; then the paper's ordering (`order`) with seeds as the unit
    (`claim` heads that column)."""
    entries = {name: Entry(name, tuple(runs)) for name, runs in groups}
    head = ["method", "seeds", "budget (min)", "grad steps", "evaluated on", *METRICS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, e in entries.items():
        if not e.runs:  # listed before its first seed has finished
            cells = ["no seed finished yet", *[NO_RECORD] * (len(head) - 3)]
            lines.append("| " + " | ".join([name, "0", *cells]) + " |")
            continue
        steps = fmt_count(entry_values(rec, e, "grad_steps", ""), _steps)
        budget = fmt_count(entry_values(rec, e, "budget", ""), _minutes)
        for i, (kind, label) in enumerate(sets):
            first = [name, str(len(e.runs)), budget, steps] if i == 0 else ["", "", "", ""]
            cells = [seed_cell(entry_values(rec, e, kind, m), m) for m in METRICS]
            lines.append("| " + " | ".join([*first, label, *cells]) + " |")
    lines += [
        "",
        "mean +- standard error over seeds (worst seed): one value per seed"
        + (" (the 192 validation tasks pooled per seed)" if "val8" in dict(sets) else "")
        + ", seeds as the unit. Folders: "
        + "; ".join(
            f"{n}: " + (", ".join(f"`{r}`" for r in e.runs) or "none yet")
            for n, e in entries.items()
        )
        + ".",
        "",
        f"| {claim} | evaluated on | A - B over seeds (mean +- se) | seeds | as measured |",
        "|---|---|---|---|---|",
    ]
    for a, b in order:
        if a not in entries or b not in entries:
            continue
        empty = [n for n in (a, b) if not entries[n].runs]
        if empty:
            lines.append(f"| {a} > {b} | every set | - | 0 | no seed of {empty[0]} finished yet |")
            continue
        for kind, label in sets:
            va = entry_values(rec, entries[a], kind, "SR")
            vb = entry_values(rec, entries[b], kind, "SR")
            if isinstance(va, str) or isinstance(vb, str):
                lines.append(f"| {a} > {b} | {label} | {MISSING} | - | - |")
                continue
            d = seed_difference(va, vb)
            cell = "-" if d is None else f"{signed(d[0])} +- {d[1]:.2f}"
            n = min(len(va), len(vb))
            lines.append(f"| {a} > {b} (SR) | {label} | {cell} | {n} | {verdict(d)} |")
    lines += [
        "",
        "A - B: seed i of A against seed i of B (the same seed number, not the same random "
        "stream), mean and standard error of those differences; 'holds' / 'does not hold' when "
        "the 95 % Student t interval over seeds excludes 0, else 'cannot be told apart'; no "
        f"verdict below {MIN_VERDICT_SEEDS} seeds each (the difference is still shown).",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------- the seeds' learning curves

# the learning harness's evaluation points of the five-seed runs (every 6 minutes)
CURVE_MINUTES = (6, 12, 18, 24)
# values of a curve point shown per method: key in curve.json's points, label
CURVE_VALUES = (
    ("val_SR", "SR, 24 validation tasks"),
    ("val_CFR", "CFR, 24 validation tasks"),
    ("test_SR", "SR, 24 test tasks"),
)
FIRST_SUCCESS = "first_success_min"


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


def first_success_cell(rec: Records, runs: Sequence[str]) -> str:
    """Minutes to the first successful training episode from the task's start (curve.json
    `time_to.train.first_success`), over seeds; seeds that never got one are counted."""
    curves = [rec.read(f"{run}/curve.json") for run in runs]
    if any(c is None for c in curves):
        return MISSING
    hits = [c["time_to"]["train"]["first_success"] for c in curves]
    found = [Stat(h["minutes"]) for h in hits if h is not None]
    never = len(hits) - len(found)
    if not never:
        return seed_cell(found, FIRST_SUCCESS)
    if not found:
        return "never"
    mean = sum(s.value for s in found) / len(found)
    return f"{f2(mean)} over {len(found)} seed(s) (worst: never, on {never})"


def short_verdict(diff: tuple[float, float, int] | None) -> str:
    v = verdict(diff)
    return (
        "no verdict" if v.startswith("fewer") else v.replace("does not hold (B ahead)", "B ahead")
    )


def render_seed_curves(
    rec: Records, groups: Sequence[tuple[str, Sequence[str]]] = CURVE_SEED_GROUPS
) -> str:
    """Where the methods differ in time: the learning harness's evaluation points of the
    five-seed runs, mean +- standard error over seeds (worst seed), and the paper's ordering at
    each point with seeds as the unit."""
    mins = [f"{m:g} min" for m in CURVE_MINUTES]
    head = ["method", "seeds", "value", *mins, "first training success (min)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    runs = {name: tuple(r) for name, r in groups}
    for name, rr in runs.items():
        for i, (key, label) in enumerate(CURVE_VALUES):
            metric = key.split("_", 1)[1]
            cells = [seed_cell(curve_values(rec, rr, m, key), metric) for m in CURVE_MINUTES]
            first = [name, str(len(rr))] if i == 0 else ["", ""]
            last = first_success_cell(rec, rr) if i == 0 else ""
            lines.append("| " + " | ".join([*first, label, *cells, last]) + " |")
    lines += [
        "",
        "| paper's claim | value | " + " | ".join(mins) + " |",
        "|" + "---|" * (2 + len(mins)),
    ]
    for a, b in PAPER_ORDER:
        if a not in runs or b not in runs:
            continue
        for key, label in CURVE_VALUES:
            cells = []
            for m in CURVE_MINUTES:
                va, vb = curve_values(rec, runs[a], m, key), curve_values(rec, runs[b], m, key)
                if isinstance(va, str) or isinstance(vb, str):
                    cells.append(MISSING)
                    continue
                d = seed_difference(va, vb)
                cell = "-" if d is None else f"{signed(d[0])} +- {d[1]:.2f}, {short_verdict(d)}"
                cells.append(cell)
            lines.append(f"| {a} > {b} | {label} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Each run's own evaluations during training (`points` of its curve.json: the policy after "
        "two adaptation episodes on 24 validation tasks of task seed 0, which the 192-task "
        "validation set (task seeds 1-8) does not contain, and on the 24 test tasks), at the "
        "point nearest each minute of training; first training success: the minutes to the first "
        "training episode that reached the goal from the task's start (`time_to.train`). Pairs: "
        "A - B over the seeds both methods have, as in the table above (holds / B ahead when the "
        "95 % t interval "
        f"excludes 0; no verdict below {MIN_VERDICT_SEEDS} seeds each).",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------- the main command's seeds

# recipes tried for the README's main command (`python -m experiments.restaurant`, the `default`
# preset, 75 iterations), each on the seeds listed: label, ((seed, folder under
# results/restaurant), ...).
# Commands: experiments/campaigns/main-*.json (`python -m experiments.campaign FILE`).
# the recipes run on all ten seeds 0-9: (seed, folder under results/restaurant)
MAIN_DEFAULT = ((0, "main-default"), *((s, f"main-seeds/default-s{s}") for s in range(1, 10)))
MAIN_RS1 = tuple((s, f"main-seeds/rs1-alpha02-s{s}") for s in range(10))
MAIN_IT95 = tuple((s, f"main-seeds/default-it95-s{s}") for s in range(10))
MAIN_RS1_IT95 = tuple((s, f"main-seeds/rs1-alpha02-it95-s{s}") for s in range(10))
MAIN_SEEDS: tuple[tuple[str, tuple[tuple[int, str], ...]], ...] = (
    ("`default`", MAIN_DEFAULT),
    (
        "+ MPC warm start for 20 iterations (`train.mpc_demo_share=1.0`, "
        "`train.mpc_demo_iterations=20`)",
        ((0, "main-seeds/warmstart20-s0"),),
    ),
    (
        "+ three posterior-phase episodes per task (`train.posterior_episodes=3`)",
        ((1, "main-seeds/posterior3-s1"), (2, "main-seeds/posterior3-s2")),
    ),
    (
        "+ three posterior-phase episodes + entropy target 0 (`pearl.target_entropy=0.0`)",
        ((1, "main-seeds/post3-tent0-s1"), (2, "main-seeds/post3-tent0-s2")),
    ),
    ("+ entropy target 0", ((2, "main-seeds/tent0-s2"),)),
    (
        "+ Adam step 1e-3 on log alpha (`pearl.alpha_lr`, since removed)",
        ((2, "main-seeds/alpha-lr1e-3-s2"),),
    ),
    (
        "+ 8 tasks per gradient step, 70 iterations (`pearl.meta_batch=8`, `train.iterations=70`)",
        ((1, "main-seeds/mb8-it70-s1"),),
    ),
    (
        "+ fixed temperature, alpha 1 (`pearl.auto_entropy=false`: temperature 1 / reward scale 5)",
        ((1, "main-seeds/fixed1-s1"), (2, "main-seeds/fixed1-s2")),
    ),
    (
        "+ fixed temperature, reward scale 10 (`pearl.auto_entropy=false`, "
        "`pearl.reward_scale=10`: as alpha 0.5)",
        ((1, "main-seeds/fixed-rs10-s1"), (2, "main-seeds/fixed-rs10-s2")),
    ),
    (
        "+ target V updated 4x faster (`pearl.tau=0.02`; paper 0.005)",
        ((1, "main-seeds/tau02-s1"), (2, "main-seeds/tau02-s2")),
    ),
    (
        "+ reward scale 1 and alpha starting at 0.2 (`pearl.reward_scale=1`, "
        "`pearl.init_alpha=0.2`: for the same Q the actor's and alpha's steps are those of scale 5 "
        "and alpha 1, while the Q and V targets are 5x smaller; its alpha is on the scale-1 "
        "footing, x5 to compare)",
        MAIN_RS1,
    ),
    (
        "`default`, 95 iterations (`--iterations 95`; seeds 2-9 resumed from their 75-iteration "
        "checkpoints)",
        MAIN_IT95,
    ),
    (
        "reward scale 1, alpha starting at 0.2, 95 iterations (resumed from the 75-iteration "
        "checkpoints)",
        MAIN_RS1_IT95,
    ),
)


def _lift_off(rows: list[dict]) -> tuple[str, str, str]:
    """From a run's metrics.jsonl: the first iteration with a successful training episode from
    the task's start, the mean success share of the last 10 iterations' such episodes, and the
    lowest alpha with its iteration."""
    first = next((r["iteration"] for r in rows if r["train_success"] > 0), None)
    last = sum(r["train_success"] for r in rows[-10:]) / len(rows[-10:])
    if "alpha" not in rows[0]:  # a fixed temperature: no alpha is logged
        return ("never" if first is None else str(first), f2(last), "fixed")
    low = min(rows, key=lambda r: r["alpha"])
    return (
        "never" if first is None else str(first),
        f2(last),
        f"{low['alpha']:.2f} (it {low['iteration']})",
    )


def render_main_seeds(rec: Records, groups=MAIN_SEEDS) -> str:
    """Per recipe and seed: when the robot first reached the goal from the task's start in
    training, how low alpha fell, and the test and validation scores."""
    head = [
        "recipe",
        "seed",
        "first success (iteration)",
        "success, last 10 iterations",
        "lowest alpha",
        "test SR / CFR",
        "val SR, 192 tasks",
        "folder",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, runs in groups:
        for i, (seed, run) in enumerate(runs):
            rows = rec.read(f"restaurant/{run}/metrics.jsonl")
            first, last, low = (MISSING,) * 3 if rows is None else _lift_off(rows)
            e = Entry(label, (f"restaurant/{run}",))
            test, val = pair_cell(rec, e, "test"), val8_cell(rec, e, cfr=True)
            name = label if i == 0 else ""
            cells = [name, str(seed), first, last, low, test, val, f"`{run}`"]
            lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "first success: the first iteration with a training episode that reached the goal from "
        "the task's start (`train_success` in metrics.jsonl; exploring starts not counted, "
        "episodes the MPC drove counted); success, last 10 iterations: the mean share of those "
        "episodes that reached the goal over the last 10 iterations; lowest alpha: the automatic "
        "entropy weight's minimum over the run (it starts at 1 unless the recipe says otherwise; "
        "fixed: no automatic tuning). "
        "test: the 24 test tasks after two adaptation episodes; val: the 192 validation tasks "
        "(task seeds 1-8), +- the standard error over tasks. Each row is one run of 75 "
        "iterations unless its recipe says otherwise.",
    ]
    return "\n".join(lines)


# the recipes of the main command run on all ten seeds 0-9, compared with seeds as the unit
MAIN_SEED_SUMMARY: tuple[tuple[str, tuple[str, ...]], ...] = tuple(
    (name, tuple(f"restaurant/{run}" for _, run in runs))
    for name, runs in (
        ("`default`", MAIN_DEFAULT),
        ("reward scale 1, init alpha 0.2", MAIN_RS1),
        ("`default`, 95 iterations", MAIN_IT95),
        ("reward scale 1, init alpha 0.2, 95 iterations", MAIN_RS1_IT95),
    )
)
MAIN_SEED_SETS = (("val8", "192 validation tasks"), ("test", "24 test tasks"))
MAIN_PASS = 0.3  # the main command's threshold on test and validation SR


def render_main_seed_summary(
    rec: Records, groups: Sequence[tuple[str, Sequence[str]]] = MAIN_SEED_SUMMARY
) -> str:
    """The main command's recipes over seeds 0-9: the seed table of `render_seeds` on the
    validation and test tasks, each recipe against the first group (the baseline) seed by seed,
    and per recipe the seeds that reach `MAIN_PASS` on both."""
    order = tuple((name, groups[0][0]) for name, _ in groups[1:])
    lines = [render_seeds(rec, groups, MAIN_SEED_SETS, order, "A > B"), ""]
    lines += [
        f"| recipe | seeds with test SR and val SR >= {MAIN_PASS} |",
        "|---|---|",
    ]
    for name, runs in groups:
        e = Entry(name, tuple(runs))
        test, val = entry_values(rec, e, "test", "SR"), entry_values(rec, e, "val8", "SR")
        if isinstance(test, str) or isinstance(val, str):
            cell = MISSING
        else:
            passed = sum(
                t.value >= MAIN_PASS and v.value >= MAIN_PASS
                for t, v in zip(test, val, strict=True)
            )
            cell = f"{passed} of {len(test)}"
        lines.append(f"| {name} | {cell} |")
    return "\n".join(lines)


# ---------------------------------------------------------------- the sidewalk's seeds

# the sidewalk's seeds (`python -m experiments.campaign experiments/campaigns/sidewalk-seeds.json`,
# `--preset cpu-auto` with the data windows kept, 30 minutes alone per seed): method -> its seed
# folders (seeds 0, 1, ... in order), listed once the run has finished
SIDEWALK_SEED_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "MPC-PEARL 0.2",
        (
            "sidewalk/seeds/mpc-pearl-s0",
            "sidewalk/seeds/mpc-pearl-s1",
            "sidewalk/seeds/mpc-pearl-s2",
        ),
    ),
    ("PEARL", ("sidewalk/seeds/pearl-s0", "sidewalk/seeds/pearl-s1", "sidewalk/seeds/pearl-s2")),
)
# the sidewalk's evaluation sets (Zara 01): online adaptation is the paper's sidewalk protocol
SIDEWALK_SEED_SETS = (
    ("online", "6 test windows, online"),
    ("test", "6 test windows, after two adaptation episodes"),
    ("ood", "5 windows with annotation holes"),
)
SIDEWALK_ORDER = (("MPC-PEARL 0.2", "PEARL"),)


def render_sidewalk_seeds(
    rec: Records, groups: Sequence[tuple[str, Sequence[str]]] = SIDEWALK_SEED_GROUPS
) -> str:
    """The sidewalk's seed table: as `render_seeds`, on the sidewalk's windows."""
    return render_seeds(rec, groups, SIDEWALK_SEED_SETS, SIDEWALK_ORDER)


BLOCKS: tuple[tuple[str, str, Callable[[Records], str]], ...] = (  # file, block name, renderer
    ("README.md", "quality", render_quality),
    ("results/README.md", "restaurant", render_restaurant),
    ("results/README.md", "robustness", render_robustness),
    ("results/README.md", "robustness-choice", render_robustness_choice),
    ("results/README.md", "seeds", render_seeds),
    ("results/README.md", "seed-curves", render_seed_curves),
    ("results/README.md", "main-seeds", render_main_seeds),
    ("results/README.md", "main-seed-summary", render_main_seed_summary),
    ("results/README.md", "sidewalk-seeds", render_sidewalk_seeds),
)


def markers(name: str) -> tuple[str, str]:
    return f"<!-- table:{name} -->", f"<!-- /table:{name} -->"


def replace_block(text: str, name: str, body: str) -> str:
    """`text` with the lines between the block's two markers replaced by `body` (ValueError if
    the markers are not there exactly once each, in order)."""
    start, end = markers(name)
    if text.count(start) != 1 or text.count(end) != 1 or text.index(start) > text.index(end):
        raise ValueError(f"expected one {start} ... {end} block")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{start}\n{body}\n{end}{tail}"


Block = tuple[str, str, Callable[[Records], str]]  # (file under the root, block name, renderer)


def generate(
    results: Path, blocks: Sequence[Block] | None = None
) -> tuple[dict[Path, tuple[str, str]], list[str]]:
    """{README path: (committed text, generated text)} and the missing records; the READMEs
    are found beside `results` (README.md) and in it (results/README.md)."""
    rec = Records(results)
    root = results.parent
    out: dict[Path, tuple[str, str]] = {}
    for rel, name, render in BLOCKS if blocks is None else blocks:
        path = root / rel
        old = out[path][1] if path in out else path.read_text()
        new = replace_block(old, name, render(rec))
        out[path] = (out[path][0] if path in out else old, new)
    return out, rec.missing


# results/ paths as the READMEs write them: from the repository root, from results/, and run
# folders from results/restaurant/ ("ablation/...")
_REF_PREFIXES = ("results/", "restaurant/", "sidewalk/", "ablation/", "gp_mpc/", "earlier/")


def referenced_paths(text: str) -> list[str]:
    """The results/ paths a README names in `code`, [brackets] or link targets (outside fenced
    code blocks), except the folder after --out in a command."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    spans = re.findall(r"`([^`]+)`", text) + re.findall(r"\[([^\]\n]+)\]", text)
    spans += re.findall(r"\]\(([^)\s]+)\)", text)
    found: list[str] = []
    for span in spans:
        toks = span.replace(",", " ").replace("`", " ").split()
        for i, tok in enumerate(toks):
            tok = tok.rstrip(";:)")
            if i and toks[i - 1] == "--out" or any(c in tok for c in "<>*{}"):
                continue
            if tok.startswith(_REF_PREFIXES) and tok not in found:
                found.append(tok)
    return found


def missing_references(root: Path) -> list[str]:
    """'README: path' for every results/ path the two READMEs name that does not exist."""
    bases = (root, root / "results", root / "results" / "restaurant")
    out = []
    for rel in ("README.md", "results/README.md"):
        for ref in referenced_paths((root / rel).read_text()):
            if not any((b / ref).exists() for b in bases):
                out.append(f"{rel}: {ref}")
    return out


def _paired_record(arg: str) -> dict:
    p = Path(arg)
    if p.is_dir():
        p = p / VAL8
    if not p.is_file():
        raise FileNotFoundError(f"{arg}: no pooled validation record ({p})")
    return json.loads(p.read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m experiments.table",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("results", nargs="?", type=Path, default=Path("results"))
    ap.add_argument("--check", action="store_true", help="compare only; exit 1 on a difference")
    ap.add_argument("--paired", nargs=2, metavar=("A", "B"), help="run folders or pooled records")
    args = ap.parse_args(argv)
    if args.paired:
        try:
            a, b = (_paired_record(x) for x in args.paired)
            print(f"SR, A - B: {paired_difference(a, b)}")
        except (OSError, ValueError, KeyError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        return 0
    files, missing = generate(args.results)
    changed = [(p, old, new) for p, (old, new) in files.items() if old != new]
    for p, old, new in changed:
        if args.check:
            sys.stdout.writelines(
                difflib.unified_diff(
                    old.splitlines(True), new.splitlines(True), f"{p} (committed)", f"{p} (records)"
                )
            )
        else:
            p.write_text(new)
            print(f"wrote {p}")
    for m in missing:
        print(f"missing record: {m}", file=sys.stderr)
    bad_refs = missing_references(args.results.parent) if args.check else []
    for ref in bad_refs:
        print(f"no such path: {ref}", file=sys.stderr)
    if missing:
        print(f"{len(missing)} record(s) missing: their cells read {MISSING}", file=sys.stderr)
    if args.check and changed:
        print(
            "the tables differ from the records: run python -m experiments.table", file=sys.stderr
        )
    return 1 if missing or bad_refs or (args.check and changed) else 0


if __name__ == "__main__":
    raise SystemExit(main())
