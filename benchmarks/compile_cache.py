"""The persistent compilation cache across processes: every program the main command compiles,
its compile time with an empty cache folder and in a second run on the same folder, side by side.

Runs `python -m experiments.restaurant --iterations N` (the README's main command, `default`
preset, N = 2 unless given) twice, one process after the other, each into a new run folder,
both with MPCPEARL_JAX_CACHE naming the same new folder (`mpcpearl_jax.compilation_cache`): the
first run (cold) compiles and writes the cache, the second (warm) reads it. Each process reports
every XLA compilation it makes (JAX's `/jax/core/compile/backend_compile_duration` event, with
the program's name, and what JAX's cache did with it: read it back, wrote it, or would not
write it because it calls back to the host or compiled in under
`compilation_cache.MIN_COMPILE_TIME_S`), and the time spent tracing and lowering to XLA, which a
cache read does not save. The programs of the two runs are paired by name and order of
compilation. Per run also: the first iteration's seconds (its collection and its gradient
steps, metrics.jsonl), the second iteration's, the whole process's wall time (start-up, the
final evaluation and writing included), and after each run the cache folder's entries and size.
The record gives the ratio warm / cold of the first iteration (target <= 0.35) and of the
process.

    python -m benchmarks.compile_cache [--tiny] [--iterations N] [--record | --out DIR]

--tiny: the smoke preset for one iteration (the tests). The record goes to the scratch folder
unless --record (benchmarks/results/compile_cache.json) or --out DIR.
"""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from benchmarks import harness

ROOT = Path(__file__).resolve().parents[1]
TARGET = 0.35  # the second run's first iteration / the first run's
# programs that compiled for at least this long in one of the runs get a row of their own in
# the printed table (the rest, mostly single operations run eagerly, share one row); the record
# lists every program
ROW_MIN_S = 1.0
# the environment variable naming the file a watched process writes its compilations to
WATCH_ENV = "MPCPEARL_BENCH_COMPILES"
# what JAX's cache did with a program, from its log lines (jax._src.compiler and
# jax._src.compilation_cache, DEBUG): the log line's start -> the program's cache status
_CACHE_LINES = (
    ("Persistent compilation cache hit", "read"),
    ("Writing ", "written"),
    ("Not writing persistent cache entry for '", None),  # the reason follows
)
_REASONS = (("host callbacks", "host callback"), ("seconds to compile", "too short"))
_CHILD = "from benchmarks.compile_cache import watched_main; watched_main()"


# ------------------------------------------------------------------ the watched process
class _CompileWatch(logging.Handler):
    """Collects every XLA compilation of this process: {program, compile_s, lower_s, cache}
    (cache: read, written, host callback, too short, or None where no cache was consulted),
    and the seconds of tracing, lowering and compiling in all."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.mu = threading.Lock()  # not `lock`: logging.Handler holds that one in emit
        self.pending: dict[int, dict[str, Any]] = {}  # per thread: the compilation under way
        self.programs: list[dict[str, Any]] = []
        self.totals = {"trace_s": 0.0, "lower_s": 0.0, "compile_s": 0.0}

    def emit(self, record: logging.LogRecord) -> None:
        msg = record.getMessage()
        for start, status in _CACHE_LINES:
            if msg.startswith(start):
                if status is None:
                    status = next((s for key, s in _REASONS if key in msg), "not written")
                with self.mu:
                    self.pending.setdefault(threading.get_ident(), {})["cache"] = status
                return

    def event(self, event: str, duration: float, **kwargs: Any) -> None:
        from jax._src import dispatch

        ident = threading.get_ident()
        with self.mu:
            if event == dispatch.JAXPR_TRACE_EVENT:
                self.totals["trace_s"] += duration
            elif event == dispatch.JAXPR_TO_MLIR_MODULE_EVENT:
                self.totals["lower_s"] += duration
                self.pending.setdefault(ident, {})["lower_s"] = duration
            elif event == dispatch.BACKEND_COMPILE_EVENT:
                self.totals["compile_s"] += duration
                seen = self.pending.pop(ident, {})
                self.programs.append(
                    {
                        "program": str(kwargs.get("fun_name", "?")),
                        "compile_s": duration,
                        "lower_s": seen.get("lower_s", 0.0),
                        "cache": seen.get("cache"),
                    }
                )

    def record(self) -> dict[str, Any]:
        """{programs: [...] in the order compiled, totals: {trace_s, lower_s, compile_s}}."""
        with self.mu:
            return {"programs": list(self.programs), "totals": dict(self.totals)}


def watch() -> _CompileWatch:
    """Report every later compilation of this process into the returned `_CompileWatch`."""
    from jax import monitoring

    watcher = _CompileWatch()
    for name in ("jax._src.compiler", "jax._src.compilation_cache"):
        logger = logging.getLogger(name)
        logger.setLevel(logging.DEBUG)
        logger.addHandler(watcher)
    monitoring.register_event_duration_secs_listener(watcher.event)
    return watcher


def watched_main() -> None:
    """The training command (`experiments.restaurant`, argv from sys.argv[1:]) with every
    compilation reported into the file $MPCPEARL_BENCH_COMPILES (JSON), written as the process
    ends, however it ends."""
    import runpy

    watcher = watch()
    sys.argv = ["experiments.restaurant", *sys.argv[1:]]
    try:
        runpy.run_module("experiments.restaurant", run_name="__main__", alter_sys=True)
    finally:
        Path(os.environ[WATCH_ENV]).write_text(json.dumps(watcher.record()))


# ------------------------------------------------------------------------------ the benchmark
def cache_figures(folder: Path) -> dict[str, Any]:
    """The cache folder's entries (programs) and their size in MB."""
    entries = [p for p in folder.glob("*-cache") if p.is_file()]
    return {"entries": len(entries), "mb": sum(p.stat().st_size for p in entries) / 1e6}


def one_run(argv: list[str], out: Path, cache: Path) -> dict[str, Any]:
    """One training command in its own process, on `cache`: its iterations' seconds, wall and
    compilations."""
    compiles = out.parent / f"{out.name}-compiles.json"
    env = {**os.environ, "MPCPEARL_JAX_CACHE": str(cache), WATCH_ENV: str(compiles)}
    cmd = [sys.executable, "-c", _CHILD, *argv, "--out", str(out)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        harness.fail(f"experiments.restaurant {' '.join(argv)} exited {done.returncode}: {tail}")
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines() if x.strip()]
    rows = [r for r in rows if "iteration" in r]
    its = [r["collect_s"] + r["update_s"] for r in rows]
    watched = json.loads(compiles.read_text())
    return {
        "process_s": wall,
        "iteration_s": its,
        "first_iteration_s": its[0],
        "first_collect_s": rows[0]["collect_s"],
        "first_update_s": rows[0]["update_s"],
        "first_mpc_solve_s": rows[0].get("mpc_solve_s"),
        "cache_after": cache_figures(cache),
        "compile_totals": {**watched["totals"], "programs": len(watched["programs"])},
        "compiles": watched["programs"],
    }


def numbered(programs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The programs with their name's occurrence in the run (1 for the first compilation of a
    name, 2 for the next...), the key that pairs a program of one run with the other's."""
    seen: Counter[str] = Counter()
    out = []
    for p in programs:
        seen[p["program"]] += 1
        out.append({**p, "occurrence": seen[p["program"]]})
    return out


def side_by_side(cold: list[dict[str, Any]], warm: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per program compiled in either run, in the cold run's order (then the warm run's
    own): name, occurrence, compile seconds cold and warm (None where that run did not compile
    it), the cache's status in each run and whether the warm run read it from the cache."""
    key = lambda p: (p["program"], p["occurrence"])  # noqa: E731
    warm_by = {key(p): p for p in numbered(warm)}
    rows, used = [], set()
    for c in numbered(cold):
        w = warm_by.get(key(c))
        used.add(key(c))
        rows.append(_pair(c, w))
    rows += [_pair(None, w) for k, w in warm_by.items() if k not in used]
    return rows


def _pair(c: dict[str, Any] | None, w: dict[str, Any] | None) -> dict[str, Any]:
    p = c or w
    assert p is not None
    return {
        "program": p["program"],
        "occurrence": p["occurrence"],
        "cold_s": None if c is None else c["compile_s"],
        "warm_s": None if w is None else w["compile_s"],
        "cold_cache": None if c is None else c["cache"],
        "warm_cache": None if w is None else w["cache"],
        "from_cache": w is not None and w["cache"] == "read",
        "host_callback": "host callback" in (c and c["cache"], w and w["cache"]),
    }


def _label(row: dict[str, Any]) -> str:
    name = re.sub(r"^jit\((.*)\)$", r"\1", row["program"])
    return name if row["occurrence"] == 1 else f"{name} #{row['occurrence']}"


def table_rows(pairs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The printed table: a row per program that compiled for ROW_MIN_S or more in a run, most
    expensive first, then the rest in one row and the sums."""
    big = [r for r in pairs if max(r["cold_s"] or 0.0, r["warm_s"] or 0.0) >= ROW_MIN_S]
    rest = [r for r in pairs if r not in big]
    big.sort(key=lambda r: -(r["cold_s"] or 0.0))
    fmt = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    out = [
        {
            "program": _label(r),
            "cold s": fmt(r["cold_s"]),
            "warm s": fmt(r["warm_s"]),
            "warm run": "read from cache"
            if r["from_cache"]
            else ("compiled (host callback)" if r["host_callback"] else (r["warm_cache"] or "-")),
        }
        for r in big
    ]
    total = lambda rs, k: sum(r[k] or 0.0 for r in rs)  # noqa: E731
    out.append(
        {
            "program": f"{len(rest)} others (< {ROW_MIN_S} s each)",
            "cold s": fmt(total(rest, "cold_s")),
            "warm s": fmt(total(rest, "warm_s")),
            "warm run": f"{sum(r['from_cache'] for r in rest)} read from cache",
        }
    )
    out.append(
        {
            "program": "all",
            "cold s": fmt(total(pairs, "cold_s")),
            "warm s": fmt(total(pairs, "warm_s")),
            "warm run": f"{sum(r['from_cache'] for r in pairs)} of {len(pairs)} read from cache",
        }
    )
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
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
                f"{r['process_s']:.1f} s, compiling {r['compile_totals']['compile_s']:.1f} s; "
                f"cache {r['cache_after']['entries']} entries, {r['cache_after']['mb']:.1f} MB",
                flush=True,
            )
    first, second = runs
    pairs = side_by_side(first["compiles"], second["compiles"])
    harness.print_table(table_rows(pairs), ["program", "cold s", "warm s", "warm run"])
    ratio = second["first_iteration_s"] / first["first_iteration_s"]
    callback = [r for r in pairs if r["host_callback"]]
    results = {
        "runs": {"first": first, "second": second},
        "programs": pairs,
        "compile_s": {"cold": first["compile_totals"], "warm": second["compile_totals"]},
        "host_callback_programs": {
            "count": len(callback),
            "cold_s": sum(r["cold_s"] or 0.0 for r in callback),
            "warm_s": sum(r["warm_s"] or 0.0 for r in callback),
        },
        "ratio_first_iteration": ratio,
        "ratio_process": second["process_s"] / first["process_s"],
        "target_ratio_first_iteration": TARGET,
        "met": ratio <= TARGET,
    }
    rows = [
        {
            "run": name,
            "first_iteration_s": r["first_iteration_s"],
            "compile_s": r["compile_totals"]["compile_s"],
            "trace_lower_s": r["compile_totals"]["trace_s"] + r["compile_totals"]["lower_s"],
            "process_s": r["process_s"],
            "cache_entries": r["cache_after"]["entries"],
            "cache_mb": r["cache_after"]["mb"],
        }
        for name, r in (("cold (empty cache)", first), ("warm (same cache)", second))
    ]
    harness.print_table(rows, list(rows[0]))
    print(
        f"warm / cold: first iteration {ratio:.2f} (target <= {TARGET}), process "
        f"{results['ratio_process']:.2f}; programs with a host callback: {len(callback)}, "
        f"compiled in both runs ({results['host_callback_programs']['warm_s']:.1f} s warm)",
        flush=True,
    )
    config = {"command": ["python", "-m", "experiments.restaurant", *command], "tiny": args.tiny}
    harness.write_record("compile_cache", config, results, args.out)
    return results


if __name__ == "__main__":
    main()
