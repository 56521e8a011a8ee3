"""Seconds per iteration of the runs of one GPU session (`benchmarks/gpu_session.sh`), against
the GPU targets.

    python -m benchmarks.gpu_summary OUT_DIR     # prints the summary; writes OUT_DIR/summary.json

Each run folder's `metrics.jsonl` has one row per training iteration: `collect_s` and `update_s`
(the iteration's two phases; with `train.pipeline` they overlap), `train_s` (seconds inside the
trainer's iterations so far) and `wall_s` (seconds since the run started, evaluations included).
An iteration's seconds are the step of `train_s` from the row before. Iterations 1 and 2 compile
(the first also fills the buffers), so the medians are over iterations 3 to the last (over the
last one alone if a run stopped before iteration 3; none if it stopped before iteration 2) and
the first iteration's seconds are given apart.

The targets (one NVIDIA H200 with 16 host cores):
- the `recipe` preset with 8 seeds (eps 0.2, 8 host workers for the MPC): at most 1.5 s per
  iteration, the faster of the runs with and without `train.pipeline`;
- one seed of the `default` preset (the main command's): at least 2x faster per iteration on the
  GPU than on the same machine's CPU, at the same number of iterations;
- the `paper` preset, one seed: at most 1.5 s per iteration.

`benchmarks.pipeline`'s and `benchmarks.collection`'s records in OUT_DIR are summarised too.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import statistics
import sys
from pathlib import Path
from typing import Any

FROM = 3  # the first timed iteration: 1 compiles and fills the buffers, 2 compiles the rest

# run folder -> what it is (the session script's folders)
RUNS: dict[str, str] = {
    "recipe": "recipe, eps 0.2",
    "recipe-pipeline": "recipe, eps 0.2, train.pipeline",
    "default-gpu": "default, on the GPU",
    "default-cpu": "default, on the same machine's CPU (JAX_PLATFORMS=cpu)",
    "paper": "paper, eps 0.2",
}
RECIPE_SEEDS = 8  # the targets count runs of these seeds (the default and paper runs: one)
RECIPE_MAX_S = 1.5
DEFAULT_MIN_SPEEDUP = 2.0
PAPER_MAX_S = 1.5
# the figures kept from benchmarks.pipeline's record
PIPELINE_KEYS = ("iterations", "timed_from", "median_wall_s", "ratio_pipeline_to_serial", "saving")


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The iteration rows of a metrics.jsonl (rows with `collect_s`), in order; a last line cut
    off by a stopped process is skipped."""
    rows = []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if "collect_s" in row:
            rows.append(row)
    return rows


def _median(xs: list[float]) -> float | None:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return statistics.median(xs) if xs else None


def run_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One run's figures from its iteration rows (`read_rows`): iterations, the first
    iteration's seconds, and the medians over the timed iterations of the iteration's seconds
    (`train_s` steps; `wall_s` steps where a row has no `train_s`), `collect_s`, `update_s` and
    the `wall_s` steps (which include evaluations)."""
    clock = "train_s" if rows and all("train_s" in r for r in rows) else "wall_s"
    iteration_s, wall_step_s, before, before_wall = [], [], 0.0, 0.0
    for r in rows:
        t = float(r.get(clock, math.nan))
        iteration_s.append(t - before)
        before = t
        w = float(r.get("wall_s", math.nan))
        wall_step_s.append(w - before_wall)
        before_wall = w
    its = [int(r.get("iteration", i + 1)) for i, r in enumerate(rows)]
    last = max(its, default=0)
    timed_from = FROM if last >= FROM else 2 if last == 2 else None
    timed = [k for k, i in enumerate(its) if timed_from is not None and i >= timed_from]

    def med(xs: list[float]) -> float | None:
        return _median([xs[k] for k in timed])

    return {
        "iterations": last,
        "timed_from": timed_from,
        "timed": len(timed),
        "first_iteration_s": iteration_s[0] if rows else None,
        "median_iteration_s": med(iteration_s),
        "median_collect_s": med([float(r["collect_s"]) for r in rows]),
        "median_update_s": med([float(r.get("update_s", math.nan)) for r in rows]),
        "median_wall_step_s": med(wall_step_s),
    }


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b <= 0 else a / b


def targets(runs: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The three GPU figures against their targets (`figure` None: not measured, or measured
    with other seeds than the target's, as in a tiny session)."""

    def it(name: str, seeds: int = 1) -> float | None:
        """A run's median iteration, if it ran the target's seeds (unknown counts)."""
        run = runs.get(name) or {}
        return run.get("median_iteration_s") if run.get("seeds", seeds) == seeds else None

    recipe = {k: it(k, RECIPE_SEEDS) for k in ("recipe-pipeline", "recipe")}
    recipe = {k: v for k, v in recipe.items() if v is not None}
    best = min(recipe, key=lambda k: recipe[k]) if recipe else None
    speedup = _ratio(it("default-cpu"), it("default-gpu"))
    rows = [
        {
            "name": "recipe_s",
            "what": "recipe, 8 seeds: seconds per iteration (the faster of the runs with and "
            "without train.pipeline)",
            "figure": recipe.get(best) if best else None,
            "run": best,
            "target": f"<= {RECIPE_MAX_S} s",
        },
        {
            "name": "default_speedup",
            "what": "default, one seed: the GPU's speed-up per iteration over the same "
            "machine's CPU",
            "figure": speedup,
            "gpu_s": it("default-gpu"),
            "cpu_s": it("default-cpu"),
            "target": f">= {DEFAULT_MIN_SPEEDUP:g}x",
        },
        {
            "name": "paper_s",
            "what": "paper, one seed: seconds per iteration",
            "figure": it("paper"),
            "target": f"<= {PAPER_MAX_S} s",
        },
    ]
    limits = {
        "recipe_s": lambda x: x <= RECIPE_MAX_S,
        "default_speedup": lambda x: x >= DEFAULT_MIN_SPEEDUP,
        "paper_s": lambda x: x <= PAPER_MAX_S,
    }
    for row in rows:
        row["met"] = None if row["figure"] is None else bool(limits[row["name"]](row["figure"]))
    return rows


def benchmark_records(out: Path) -> dict[str, Any]:
    """The main figures of `benchmarks.pipeline`'s and `benchmarks.collection`'s records in
    `out` (absent ones left out)."""
    found: dict[str, Any] = {}
    for path in sorted(out.glob("pipeline*.json")):
        res = json.loads(path.read_text()).get("results", {})
        found[path.stem] = {k: res.get(k) for k in PIPELINE_KEYS}
    for path in sorted(out.glob("collection*.json")):
        res = json.loads(path.read_text()).get("results", {})
        found[path.stem] = res.get("summary", {})
    return found


def machine(out: Path) -> dict[str, Any]:
    """What the session's machine.txt says: its lines, and the GPU's name where nvidia-smi
    gave one (None otherwise)."""
    path = out / "machine.txt"
    text = path.read_text().splitlines() if path.is_file() else []
    gpu = None
    if len(text) >= 2 and text[0].startswith("name"):  # nvidia-smi --format=csv: header, row
        gpu = text[1].split(",")[0].strip() or None
    return {"gpu": gpu, "lines": text}


def summarize(out: str | Path) -> dict[str, Any]:
    """The session's summary from the run folders and records under `out`."""
    out = Path(out)
    runs: dict[str, dict[str, Any]] = {}
    for name, what in RUNS.items():
        path = out / name / "metrics.jsonl"
        if path.is_file():
            runs[name] = {"what": what, **run_summary(read_rows(path))}
            config = out / name / "config.json"
            if config.is_file():  # what the run was given (fewer seeds in a tiny session)
                cfg = json.loads(config.read_text())
                runs[name]["seeds"] = cfg.get("seeds")
                runs[name]["pipeline"] = cfg.get("train", {}).get("pipeline")
    return {
        "out": str(out),
        "written": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "machine": machine(out),
        "timed_from": FROM,
        "runs": runs,
        "targets": targets(runs),
        "benchmarks": benchmark_records(out),
    }


def _s(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f} s"


def lines(summary: dict[str, Any]) -> list[str]:
    """The summary as text, one line per run and per target."""
    out = []
    for name in RUNS:
        r = summary["runs"].get(name)
        if r is None:
            out.append(f"{name}: no metrics.jsonl")
            continue
        n = r.get("seeds")
        seeds = "" if n is None else f", {n} seed" + ("s" if n != 1 else "")
        head = f"{name} ({r['what']}{seeds}): {r['iterations']} iteration(s)"
        first = f"first iteration {_s(r['first_iteration_s'])}"
        if not r["timed"]:
            out.append(f"{head}, none after compilation; {first}")
            continue
        timed = (
            f"iteration {r['iterations']}"
            if r["timed_from"] == r["iterations"]
            else f"iterations {r['timed_from']}-{r['iterations']}"
        )
        out.append(
            f"{head}; median over {timed}: iteration {_s(r['median_iteration_s'])}, collect "
            f"{_s(r['median_collect_s'])}, update {_s(r['median_update_s'])}, wall step "
            f"{_s(r['median_wall_step_s'])}; {first}"
        )
    for name, rec in summary["benchmarks"].items():
        out.append(f"{name}: {json.dumps(rec, sort_keys=True)}")
    for t in summary["targets"]:
        if t["figure"] is None:
            shown, verdict = "not measured", ""
        elif t["name"] == "default_speedup":
            shown = f"{t['figure']:.2f}x (GPU {_s(t['gpu_s'])}, CPU {_s(t['cpu_s'])})"
            verdict = " met" if t["met"] else " NOT met"
        else:
            shown = _s(t["figure"]) + (f" ({t['run']})" if t.get("run") else "")
            verdict = " met" if t["met"] else " NOT met"
        out.append(f"target {t['name']}: {t['what']}: {shown}; target {t['target']}{verdict}")
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path, help="the session's OUT_DIR")
    p.add_argument(
        "--json", type=Path, help="where to write the JSON (default OUT_DIR/summary.json)"
    )
    args = p.parse_args(argv)
    if not args.out.is_dir():
        p.error(f"{args.out} is not a folder")
    summary = summarize(args.out)
    path = args.json or args.out / "summary.json"
    path.write_text(json.dumps(summary, indent=1) + "\n")
    print("\n".join(lines(summary)))
    print(f"wrote {path}")
    return summary


if __name__ == "__main__":
    main(sys.argv[1:])
