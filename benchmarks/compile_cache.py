"""The persistent compilation cache across processes: the main command's first iteration in a
second run against the first, both on one new, empty cache folder.

Runs `python -m experiments.restaurant --iterations N` (the README's main command, `default`
preset, N = 2 unless given) twice, one process after the other, each into a new run folder,
both with MPCPEARL_JAX_CACHE naming the same new folder (`mpcpearl_jax.compilation_cache`): the
first run compiles and writes the cache, the second reads it. Per run: the first iteration's
seconds (its collection and its gradient steps, metrics.jsonl; the first iteration compiles the
collection's rollouts and the update), the second iteration's, the whole process's wall time
(start-up, the final evaluation and writing included), and after each run the cache folder's
entries and size. The record gives the ratio second / first of the first iteration (target
<= 0.35) and of the process.

    python -m benchmarks.compile_cache [--tiny] [--iterations N] [--record | --out DIR]

--tiny: the smoke preset for one iteration (the tests). The record goes to the scratch folder
unless --record (benchmarks/results/compile_cache.json) or --out DIR.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks import harness

ROOT = Path(__file__).resolve().parents[1]
TARGET = 0.35  # the second run's first iteration / the first run's


def cache_figures(folder: Path) -> dict[str, Any]:
    """The cache folder's entries (programs) and their size in MB."""
    entries = [p for p in folder.glob("*-cache") if p.is_file()]
    return {"entries": len(entries), "mb": sum(p.stat().st_size for p in entries) / 1e6}


def one_run(argv: list[str], out: Path, cache: Path) -> dict[str, Any]:
    """One training command in its own process, on `cache`: its iterations' seconds and wall."""
    env = {**os.environ, "MPCPEARL_JAX_CACHE": str(cache)}
    cmd = [sys.executable, "-m", "experiments.restaurant", *argv, "--out", str(out)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        harness.fail(f"{' '.join(cmd[1:])} exited {done.returncode}: {tail}")
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines() if x.strip()]
    rows = [r for r in rows if "iteration" in r]
    its = [r["collect_s"] + r["update_s"] for r in rows]
    return {
        "process_s": wall,
        "iteration_s": its,
        "first_iteration_s": its[0],
        "first_collect_s": rows[0]["collect_s"],
        "first_update_s": rows[0]["update_s"],
        "first_mpc_solve_s": rows[0].get("mpc_solve_s"),
        "cache_after": cache_figures(cache),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=None, help="default: 2 (1 at --tiny)")
    args = p.parse_args(argv)
    n = args.iterations or (1 if args.tiny else 2)
    if n < 1:
        p.error("--iterations must be at least 1")
    if args.threads is not None:
        p.error("--threads: the training command takes every core; not with this benchmark")
    command = ["--iterations", str(n), *(["--preset", "smoke"] if args.tiny else [])]
    with tempfile.TemporaryDirectory(prefix="compile-cache-") as tmp:
        cache = Path(tmp) / "cache"
        cache.mkdir()
        runs = []
        for k in (1, 2):
            runs.append(one_run(command, Path(tmp) / f"run{k}", cache))
            r = runs[-1]
            print(
                f"run {k}: first iteration {r['first_iteration_s']:.1f} s (collection "
                f"{r['first_collect_s']:.1f} s, update {r['first_update_s']:.1f} s), process "
                f"{r['process_s']:.1f} s; cache {r['cache_after']['entries']} entries, "
                f"{r['cache_after']['mb']:.1f} MB",
                flush=True,
            )
    first, second = runs
    ratio = second["first_iteration_s"] / first["first_iteration_s"]
    results = {
        "runs": {"first": first, "second": second},
        "ratio_first_iteration": ratio,
        "ratio_process": second["process_s"] / first["process_s"],
        "target_ratio_first_iteration": TARGET,
        "met": ratio <= TARGET,
    }
    rows = [
        {
            "run": name,
            "first_iteration_s": r["first_iteration_s"],
            "process_s": r["process_s"],
            "cache_entries": r["cache_after"]["entries"],
            "cache_mb": r["cache_after"]["mb"],
        }
        for name, r in (("first (empty cache)", first), ("second (warm cache)", second))
    ]
    harness.print_table(rows, list(rows[0]))
    print(
        f"second / first: first iteration {ratio:.2f} (target <= {TARGET}), process "
        f"{results['ratio_process']:.2f}",
        flush=True,
    )
    config = {"command": ["python", "-m", "experiments.restaurant", *command], "tiny": args.tiny}
    harness.write_record("compile_cache", config, results, args.out)
    return results


if __name__ == "__main__":
    main()
