"""The measuring commands' shared harness (the lab's diagnostics, `lab.harness`, and the
benchmarks, `benchmarks.harness`): their sizes (--tiny, default, --full), the cores they use
(--threads, checked, then `training.machine.configure_threads` and the platform JAX_PLATFORMS
asks for), their one-line failure, and timing: one call (`timed`), a function's repeated calls
after its first (`time_fn`) and samples' quartiles (`summarize`)."""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from mpcpearl_jax.cli.platform import PlatformError, check_platform
from mpcpearl_jax.training import machine

SIZES = ("tiny", "default", "full")


def fail(line: str) -> NoReturn:
    """End a command on a bad input with `line` as its one error line (exit code 2)."""
    print(f"error: {line}", file=sys.stderr, flush=True)
    raise SystemExit(2)


def size_of(args: argparse.Namespace) -> str:
    """'tiny', 'default' or 'full' from the parsed --tiny / --full flags."""
    return "tiny" if args.tiny else "full" if args.full else "default"


def check_threads(args: argparse.Namespace) -> str | None:
    """The one-line error of a --threads outside 1 to the cores this process may use (None when
    it is good or not given)."""
    threads = getattr(args, "threads", None)
    if threads is not None:
        cores = machine.available_cores()
        if not 1 <= threads <= cores:
            return f"--threads {threads}: this process may use 1 to {cores} cores (default: all)"
    return None


def check_platform_or_fail() -> None:
    """JAX_PLATFORMS naming a platform this machine does not have: one line, exit 2."""
    try:
        check_platform()
    except PlatformError as e:
        fail(str(e))


def configure_threads(n: int | None) -> dict[str, Any]:
    """`training.machine.configure_threads` (the same cores for JAX and PyTorch; call it before
    either starts its thread pool), then the platform JAX_PLATFORMS asks for, checked (one line,
    exit 2, if this machine lacks it)."""
    info = machine.configure_threads(n)
    check_platform_or_fail()
    return info


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """(fn(), seconds) of one call, for a one-off measurement such as a compilation."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def summarize(raw: Sequence[float]) -> dict[str, Any]:
    """Median, quartiles, min and max of raw samples (seconds)."""
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
    _, first = timed(lambda: block(fn()))
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
