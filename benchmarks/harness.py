"""Shared helpers for benchmark scripts: threads, timing, machine info, tables and JSON records.

Every script prints a table and writes a JSON record with the machine, versions, config, raw
timings, medians and ratios (measured in the same run). Scripts share the command-line flags of
`common_parser`: `--tiny` (seconds, used by the tests), default (the `benchmarks.all` size),
`--full` (the paper's sizes), `--out DIR` and `--threads N`.

Call `configure_threads` *before* JAX or PyTorch start their thread pools (i.e. before the first
JAX computation), so that both libraries get the same number of cores.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from mpcpearl_jax.training import machine
from mpcpearl_jax.training.machine import (  # noqa: F401 (re-exported)
    available_cores,
    configure_threads,
    machine_info,
    print_table,
)

DEFAULT_OUT = Path("benchmarks") / "results"
SIZES = ("tiny", "default", "full")


# ------------------------------------------------------------------------------ CLI
def common_parser(description: str) -> argparse.ArgumentParser:
    """Parser with the flags every benchmark script understands."""
    p = argparse.ArgumentParser(description=description)
    size = p.add_mutually_exclusive_group()
    size.add_argument("--tiny", action="store_true", help="seconds-long smoke run (tests)")
    size.add_argument("--full", action="store_true", help="the paper's sizes (slow)")
    p.add_argument("--out", default=str(DEFAULT_OUT), help="directory of the JSON record")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU cores for JAX and PyTorch alike (default: all cores this process may use)",
    )
    return p


def size_of(args: argparse.Namespace) -> str:
    """'tiny', 'default' or 'full' from parsed `common_parser` flags."""
    return "tiny" if args.tiny else "full" if args.full else "default"


# -------------------------------------------------------------------------- threads
def torch_threads(n: int) -> dict[str, Any] | None:
    """Import PyTorch with `n` intra-op threads; None when it is not installed."""
    try:
        import torch
    except ImportError:
        return None
    torch.set_num_threads(n)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already set in this process
        pass
    return {"torch": torch.__version__, "torch_threads": torch.get_num_threads()}


def torch_device() -> str:
    """Where the PyTorch baseline runs: on the GPU when JAX runs on one and PyTorch sees one
    (same accelerator on both sides), else on the CPU."""
    import jax
    import torch

    if jax.default_backend() == "gpu" and torch.cuda.is_available():
        return "cuda"
    return "cpu"


TORCH_MISSING = (
    "PyTorch is not installed: skipping the PyTorch comparison "
    "(install the optional extra: pip install -e '.[bench]', i.e. torch==2.13.0 CPU)"
)


# --------------------------------------------------------------------------- timing
def summarize(raw: Sequence[float]) -> dict[str, Any]:
    """Median, quartiles, min and max of raw samples."""
    xs = sorted(raw)
    q = statistics.quantiles(xs, n=4, method="inclusive") if len(xs) >= 2 else [xs[0]] * 3
    return {
        "raw_s": list(raw),
        "median_s": statistics.median(xs),
        "p25_s": q[0],
        "p75_s": q[2],
        "min_s": xs[0],
        "max_s": xs[-1],
    }


def time_fn(
    fn: Callable[[], Any],
    *,
    repeats: int = 5,
    warmup: int = 1,
    block: Callable[[Any], Any] | None = None,
    inner: int = 1,
) -> dict[str, Any]:
    """Time `fn()` `repeats` times after `warmup` calls (the first call's time = compile time).

    `block` is applied to the result to wait for asynchronous work (e.g. jax.block_until_ready).
    Each sample runs `fn` `inner` times and is divided by `inner` (seconds per call).
    Returns seconds per call: first_call_s, raw_s, median_s, p25_s, p75_s, min_s, max_s.
    """
    block = block or (lambda x: x)
    t0 = time.perf_counter()
    block(fn())
    first = time.perf_counter() - t0
    for _ in range(max(warmup - 1, 0)):
        block(fn())
    raw = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            out = fn()
        block(out)
        raw.append((time.perf_counter() - t0) / inner)
    return {"first_call_s": first, "inner": inner, **summarize(raw)}


def calls_for(seconds_per_call: float, target_s: float) -> int:
    """How many calls make one timing sample last about `target_s` seconds."""
    return max(1, int(target_s / max(seconds_per_call, 1e-9)))


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """(fn(), seconds) for a one-off measurement such as a compilation."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


# ---------------------------------------------------------------------------- output
def write_record(
    name: str, config: dict[str, Any], results: Any, out_dir: str | Path | None = None
) -> Path:
    """Write {machine, config, results} to OUT/name.json (default benchmarks/results) and
    return the path (`training.machine.write_record`)."""
    return machine.write_record(name, config, results, out_dir or DEFAULT_OUT)
