"""The README blocks as Markdown: cells (a metric over one seed or a seed group, counts,
SR / CFR pairs) and one `render_*` per table, each taking the `Records` it reads."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from lab.tables.catalogue import (
    CAMPAIGN_SEED_GROUPS,
    CURVE_MINUTES,
    CURVE_SEED_GROUPS,
    CURVE_VALUES,
    GP_MPC_ROW,
    MAIN_PASS,
    MAIN_SEED_SETS,
    MAIN_SEED_SUMMARY,
    MAIN_SEEDS,
    PAPER_ORDER,
    PERTURBATIONS,
    RESTAURANT,
    ROBUSTNESS,
    ROBUSTNESS_CHOICE,
    SEED_GROUPS,
    SEED_SETS,
    SIDEWALK_ORDER,
    SIDEWALK_SEED_GROUPS,
    SIDEWALK_SEED_SETS,
    VALIDATION_PERTURBATIONS,
    Entry,
)
from lab.tables.statistics import (
    MIN_VERDICT_SEEDS,
    MISSING,
    NO_RECORD,
    Records,
    Stat,
    curve_values,
    entry_values,
    pooled_value,
    seed_difference,
    seed_stats,
    signed,
    verdict,
)
from mpcpearl_jax.evaluation.metrics import METRIC_NAMES
from mpcpearl_jax.evaluation.metrics import METRICS as METRIC_SPECS

# ---------------------------------------------------------------- cells


def f2(x: float) -> str:
    return f"{x:.2f}"


def fmt_metric(stats: list[Stat] | str, metric: str, with_se: bool = False) -> str:
    """One metric: a single seed as the record has it (2 decimals, '+- se' over tasks where
    asked), a seed group as 'mean +- se (worst w)' over seeds."""
    if isinstance(stats, str):
        return stats
    fmt = METRIC_SPECS[metric].format if metric in METRIC_SPECS else f2
    if len(stats) == 1:
        s = stats[0]
        return fmt(s.value) + (f" +- {fmt(s.se)}" if with_se and s.se is not None else "")
    mean, se, worst = seed_stats([s.value for s in stats], metric)
    return f"{fmt(mean)} +- {fmt(se)} (worst {fmt(worst)})"


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

METRICS = METRIC_NAMES
SEEDS_NOTE = (
    "a +- b: the standard error over the 192 validation tasks for one seed; for a group of "
    "seeds, mean +- standard error over the seeds, then the worst seed."
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


# ---------------------------------------------------------------- crowd perturbations


def _perturbed_record(run: str, suffix: str) -> str:
    if run == GP_MPC_ROW:
        if not suffix:  # the unperturbed GP-MPC record of the main table
            return "gp_mpc/restaurant_val_seeds1-8.json"
        return f"gp_mpc/perturbed/val{suffix}-seeds1-8/results.json"
    return f"{run}/eval/policy-val{suffix}-seeds1-8/results.json"


def robustness_rows(rec: Records) -> list[tuple[str, str]]:
    """The robustness table's rows: ROBUSTNESS, then every other single-run entry of the main
    table and GP-MPC once evaluated under the perturbations (`lab.robustness`, whose
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
            pair = [pooled_value(rec, rel, m) for m in ("SR", "CFR")]
            cells.append(MISSING if None in pair else " / ".join(f2(p.value) for p in pair))
        ref = "" if run == GP_MPC_ROW else f" [`{run}`]"
        lines.append(f"| {label}{ref} | " + " | ".join(cells) + " |")
    return lines


def render_robustness(rec: Records, rows: Sequence[tuple[str, str]] | None = None) -> str:
    """SR / CFR of each run on the 192 validation tasks with the people's timing perturbed
    (`lab.robustness`, i.e. `experiments.evaluate RUN --split val --task-seeds 1-8
    --perturb ...`)."""
    lines = render_perturbed(rec, robustness_rows(rec) if rows is None else rows, PERTURBATIONS)
    lines += [
        "",
        "SR / CFR on the 192 validation tasks (task seeds 1-8) with every person's timing "
        "perturbed on an unchanged path: delay K holds everyone at the start K more steps, speed "
        "S follows the paths S times as fast (docs/method.md §8a). Records: "
        "`RUN/eval/policy-val[-PERTURBATION]-seeds1-8/results.json`, GP-MPC's "
        "`gp_mpc/perturbed/`; produced by `python -m lab.robustness --all --gp-mpc`.",
    ]
    return "\n".join(lines)


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


def seed_cell(stats: list[Stat] | str, metric: str) -> str:
    """'mean +- se (worst w)' over seeds; one seed alone is shown as its value '(1 seed)'."""
    if isinstance(stats, str):
        return stats
    if len(stats) == 1:
        return f"{f2(stats[0].value)} (1 seed)"
    return fmt_metric(stats, metric)


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


def render_campaign_seeds(rec: Records) -> str:
    """The five-seed table of the earlier campaign (the same recipe on an earlier version, a
    faster machine), on its six evaluation sets."""
    return render_seeds(rec, CAMPAIGN_SEED_GROUPS)


# ---------------------------------------------------------------- the seeds' learning curves


FIRST_SUCCESS = "first_success_min"


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


def render_sidewalk_seeds(
    rec: Records, groups: Sequence[tuple[str, Sequence[str]]] = SIDEWALK_SEED_GROUPS
) -> str:
    """The sidewalk's seed table: as `render_seeds`, on the sidewalk's windows."""
    return render_seeds(rec, groups, SIDEWALK_SEED_SETS, SIDEWALK_ORDER)
