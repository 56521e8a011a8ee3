"""What keeping the best of N seeds by validation would score, estimated from a seed screen's
single-seed records, without training anything.

    python -m lab.diagnostics.best_of                      # the `default` arm, N = 1-5
    python -m lab.diagnostics.best_of --arm guide --n 1 2 3 --out DIR

A product that trains N seeds in one program and keeps the one with the highest validation SR
scores that seed's test SR. If the N seeds are independent draws of the arm's single-seed runs
(seed s of a program seeded at b draws the keys of a single run seeded at b + s), every N-subset
of the screen's finished seeds is one equally likely such program. For each N this reads the
screen report (`lab.screen`: per seed the validation SR on its 192 tasks and the test SR on the
24 test tasks after two adaptation episodes), picks the validation-best seed of every subset (ties:
the lowest seed) and reports over the subsets: the share whose pick has validation and test SR both
at least the screen's PASS, the mean and lowest test SR of the picks, and the mean validation SR of
the picks (selected on it, so biased upwards; the test SR is not). The estimate is exact over the
subsets but rests on the screen's ten seeds: it cannot show a failure rarer than they do.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

REPORT = Path("results/restaurant/screen/learner.json")
OUT = Path("results/restaurant/plateau/best-of.json")


def best_of(seeds: dict[int, tuple[float, float]], n: int, passing: float) -> dict[str, Any]:
    """seeds: {seed: (val SR, test SR)}; the statistics of the validation-best seed over every
    n-subset of them."""
    if not 1 <= n <= len(seeds):
        raise ValueError(f"n = {n}: between 1 and the {len(seeds)} seeds")
    picks = []
    for subset in itertools.combinations(sorted(seeds), n):
        best = max(subset, key=lambda s: (seeds[s][0], -s))
        picks.append(best)
    val = [seeds[s][0] for s in picks]
    test = [seeds[s][1] for s in picks]
    ok = [seeds[s][0] >= passing and seeds[s][1] >= passing for s in picks]
    return {
        "n": n,
        "subsets": len(picks),
        "pass_share": sum(ok) / len(ok),
        "test_SR_mean": sum(test) / len(test),
        "test_SR_lowest": min(test),
        "val_SR_mean_of_picks": sum(val) / len(val),
    }


def arm_seeds(report: dict[str, Any], arm: str) -> dict[int, tuple[float, float]]:
    """{seed: (val SR, test SR)} of the arm's finished seeds in a `lab.screen` report."""
    if arm not in report.get("arms", {}):
        raise ValueError(f"arm {arm!r} is not in the report; arms: {sorted(report['arms'])}")
    runs = report["arms"][arm]["runs"]
    return {int(r["seed"]): (float(r["val"]["SR"]), float(r["test_SR"])) for r in runs}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab.diagnostics.best_of", description=__doc__)
    p.add_argument("--report", type=Path, default=REPORT, help="a lab.screen report (JSON)")
    p.add_argument("--arm", default="default", help="the arm whose seeds are drawn")
    p.add_argument("--n", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="seeds per program")
    p.add_argument("--out", default=str(OUT), help=f"where the JSON goes (a folder: {OUT.name})")
    args = p.parse_args(argv)
    folder = args.out.endswith(("/", os.sep))  # "DIR/": a folder, new or not
    args.out = Path(args.out) / OUT.name if folder or Path(args.out).is_dir() else Path(args.out)
    try:
        report = json.loads(args.report.read_text())
        seeds = arm_seeds(report, args.arm)
        passing = float(report["pass"])
        rows = [best_of(seeds, n, passing) for n in args.n]
    except (OSError, ValueError, KeyError) as e:
        print(f"error: {args.report}: {e}", file=sys.stderr)
        return 2
    out = {
        "report": str(args.report),
        "arm": args.arm,
        "pass": passing,
        "seeds": {str(s): {"val_SR": v, "test_SR": t} for s, (v, t) in sorted(seeds.items())},
        "best_of": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"best of N by validation SR, arm {args.arm!r}, {len(seeds)} seeds ({args.report})")
    print(f"| N | programs | val and test SR >= {passing:.1f} | test SR mean | lowest |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['n']} | {r['subsets']} | {r['pass_share']:.2f} | {r['test_SR_mean']:.2f} "
            f"| {r['test_SR_lowest']:.2f} |"
        )
    print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
