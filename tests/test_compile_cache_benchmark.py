"""`benchmarks.compile_cache`: every compilation of a process with what JAX's persistent cache
did with it (read back, written, not written because of a host callback), the programs of a
cold and a warm run paired side by side, and the record of the benchmark's tiny mode."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import compile_cache as bench

ROOT = Path(__file__).resolve().parents[1]

# one program without and one with a host callback, compiled under the watch on `folder`
_PROGRAM = """
import json, sys
import jax, jax.numpy as jnp, numpy as np
from benchmarks.compile_cache import watch
watcher = watch()
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
def plain(x):
    for i in range(20):
        x = jnp.sin(x * (i + 1.0)) + 1e-3 * jnp.cos(x[::-1])
    return x
def calls_back(x):
    out = jax.ShapeDtypeStruct(x.shape, x.dtype)
    return jax.pure_callback(lambda a: np.asarray(a) + 1.0, out, x) * 2.0
x = jnp.linspace(0.0, 1.0, 16)
jax.block_until_ready((jax.jit(plain)(x), jax.jit(calls_back)(x)))
print(json.dumps(watcher.record()))
"""


def _watched(folder: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    done = subprocess.run(
        [sys.executable, "-c", _PROGRAM, str(folder)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_warm_run_reads_the_plain_program_and_compiles_the_callback_again(tmp_path):
    cold, warm = _watched(tmp_path / "cache"), _watched(tmp_path / "cache")
    for run in (cold, warm):
        assert run["totals"]["compile_s"] == pytest.approx(
            sum(p["compile_s"] for p in run["programs"])
        )
        assert run["totals"]["trace_s"] > 0 and run["totals"]["lower_s"] > 0
    pairs = {p["program"]: p for p in bench.side_by_side(cold["programs"], warm["programs"])}
    plain, calls_back = pairs["jit(plain)"], pairs["jit(calls_back)"]
    assert plain["cold_cache"] == "written" and plain["warm_cache"] == "read"
    assert plain["from_cache"] and not plain["host_callback"]
    assert calls_back["cold_cache"] == calls_back["warm_cache"] == "host callback"
    assert calls_back["host_callback"] and not calls_back["from_cache"]
    for p in (plain, calls_back):
        assert p["cold_s"] > 0 and p["warm_s"] > 0 and p["occurrence"] == 1


def test_programs_pair_by_name_and_order():
    prog = lambda name, s, cache: {"program": name, "compile_s": s, "lower_s": 0.0, "cache": cache}  # noqa: E731
    cold = [
        prog("jit(a)", 2.0, "written"),
        prog("jit(c)", 3.0, "host callback"),
        prog("jit(c)", 1.0, "host callback"),
        prog("jit(b)", 0.5, "too short"),
    ]
    warm = [
        prog("jit(a)", 0.05, "read"),
        prog("jit(c)", 2.5, "host callback"),
        prog("jit(c)", 1.5, "host callback"),
        prog("jit(d)", 1.2, "written"),
    ]
    pairs = bench.side_by_side(cold, warm)
    assert [(p["program"], p["occurrence"]) for p in pairs] == [
        ("jit(a)", 1),
        ("jit(c)", 1),
        ("jit(c)", 2),
        ("jit(b)", 1),
        ("jit(d)", 1),
    ]
    assert pairs[2]["cold_s"] == 1.0 and pairs[2]["warm_s"] == 1.5 and pairs[2]["host_callback"]
    assert pairs[3]["warm_s"] is None and pairs[4]["cold_s"] is None
    rows = bench.table_rows(pairs)
    assert [r["program"] for r in rows[:4]] == ["c", "a", "c #2", "d"]  # dearest first
    assert rows[1]["warm run"] == "read from cache"
    assert rows[0]["warm run"] == "compiled (host callback)"
    assert rows[-2]["program"].startswith("1 others") and rows[-1]["program"] == "all"
    assert rows[-1]["cold s"] == f"{6.5:.2f}" and rows[-1]["warm s"] == f"{5.25:.2f}"


@pytest.mark.slow
def test_the_benchmark_runs_tiny(tmp_path):
    """`benchmarks.compile_cache --tiny`: two smoke trainings on one new cache, every program
    of each, paired: the warm run reads the programs without a host callback from the cache
    and compiles the collection's (which call the MPC) again."""
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "benchmarks.compile_cache", "--tiny", "--out", str(out)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert done.returncode == 0, done.stderr
    assert "| program | cold s | warm s | warm run |" in done.stdout
    rec = json.loads((out / "compile_cache.json").read_text())["results"]
    first, second = rec["runs"]["first"], rec["runs"]["second"]
    assert first["cache_after"]["entries"] > 0
    grown = second["cache_after"]["entries"] - first["cache_after"]["entries"]
    assert 0 <= grown < first["cache_after"]["entries"]
    assert rec["ratio_first_iteration"] == pytest.approx(
        second["first_iteration_s"] / first["first_iteration_s"]
    )
    programs = rec["programs"]
    keys = {
        "program",
        "occurrence",
        "cold_s",
        "warm_s",
        "cold_cache",
        "warm_cache",
        "from_cache",
        "host_callback",
    }
    assert programs and all(set(p) == keys for p in programs)
    assert len(programs) >= max(len(first["compiles"]), len(second["compiles"]))
    for name, run in (("cold", first), ("warm", second)):
        assert rec["compile_s"][name]["compile_s"] == pytest.approx(
            sum(p["compile_s"] for p in run["compiles"])
        )
    collect = [p for p in programs if p["program"] == "jit(_collect_phase)"]
    assert collect and all(p["host_callback"] and not p["from_cache"] for p in collect)
    assert all(p["warm_s"] is not None for p in collect)  # compiled again in the warm run
    update = [p for p in programs if p["program"] == "jit(_update_steps)"]
    assert update and all(p["from_cache"] for p in update)
    assert rec["host_callback_programs"]["count"] == len(collect)
