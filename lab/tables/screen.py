"""The table of a seed screen (`lab.screen`): one row per arm, made from the screen's run
folders (its report `<results>/<name>.json` only saves recomputing a bootstrap whose inputs have
not changed). An arm with unfinished seeds shows the finished ones and says how many of how
many; nothing is filled in."""

from __future__ import annotations

from pathlib import Path

from lab.screen import PASS, load_screen, read_report, screen_report
from lab.tables.statistics import Records

NONE = "-"


def _f2(x: float) -> str:
    return f"{x:.2f}"


def _mean_se(stats: dict | None) -> str:
    if stats is None:
        return NONE
    se = stats["se"]
    return _f2(stats["mean"]) + ("" if se is None else f" +- {_f2(se)}")


def _interval(entry: dict | None) -> str:
    if entry is None:
        return NONE
    lo, hi = entry["ci"]
    return f"{_f2(entry['value'])} [{_f2(lo)}, {_f2(hi)}]"


def _steps(x: float | None) -> str:
    return NONE if x is None else str(int(round(x)))


def render_screen_report(report: dict) -> str:
    """The Markdown table of a screen's report: validation SR over seeds, IQM and probability of
    improvement with their intervals, lift-off, passes; then the same for validation SPL."""
    base = report["baseline"]
    lines = [
        "| arm | seeds | lifted off | median lift-off (gradient steps) | val SR | worst seed "
        "| IQM val SR [95 % CI] | P(better than baseline) val SR [95 % CI] "
        f"| val SR and test SR >= {PASS} | val CFR | val TT | val SPL |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    spl = [
        "| arm | IQM val SPL [95 % CI] | P(better than baseline) val SPL [95 % CI] |",
        "|---|---|---|",
    ]
    for name, arm in report["arms"].items():
        n, total = len(arm["finished"]), len(arm["seeds"])
        seeds = str(n) if n == total else f"{n}/{total} seeds"
        val = arm["val"] or {}
        poi = {m: _interval(e) for m, e in arm["improvement"].items()}
        if name == base:
            poi = {m: "(baseline)" for m in poi}
        median = arm["liftoff"]["grad_steps"]["median"] if arm["liftoff"] else None
        worst = NONE if not val else _f2(val["SR"]["worst"])
        cells = [
            f"`{name}`",
            seeds,
            f"{arm['lifted']}/{n}",
            _steps(median),
            _mean_se(val.get("SR")),
            worst,
            _interval(arm["iqm"]["SR"]),
            poi["SR"],
            f"{arm['passed']} of {n}",
            _mean_se(val.get("CFR")),
            _mean_se(val.get("TT")),
            _mean_se(val.get("SPL")),
        ]
        lines.append("| " + " | ".join(cells) + " |")
        spl.append(f"| `{name}` | {_interval(arm['iqm']['SPL'])} | {poi['SPL']} |")
    return "\n".join([*lines, "", *spl])


def render_screen(rec: Records, screen_file: str) -> str:
    """The table of the screen file `screen_file` (a path from the repository root, the folder
    above `rec.results`), from its run folders."""
    root = rec.results.parent
    screen = load_screen(root / screen_file)
    report = screen_report(screen, root, read_report(root / screen.report_path))
    return render_screen_report(report)


def render_screen_learner(rec: Records) -> str:
    return render_screen(rec, str(Path("lab") / "screens" / "learner.json"))
