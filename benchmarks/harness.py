"""Shared helpers for benchmark scripts: timing, machine info, tables and JSON records.

Every script prints a table and writes a JSON record with the machine, versions, config, raw
timings, medians and ratios (measured in the same run).
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

DEFAULT_OUT = Path("benchmarks") / "results"


def machine_info() -> dict[str, Any]:
    """CPU, thread and library versions of this run."""
    info: dict[str, Any] = {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
    }
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    for mod in ("jax", "jaxlib", "flax", "optax", "numpy", "osqp", "torch"):
        try:
            info[mod] = __import__(mod).__version__
        except Exception:  # noqa: BLE001 - optional packages
            pass
    try:
        import jax

        info["jax_devices"] = [str(d) for d in jax.devices()]
    except Exception:  # noqa: BLE001
        pass
    return info


def time_fn(
    fn: Callable[[], Any], *, repeats: int = 5, warmup: int = 1, block: Callable[[Any], Any] | None = None
) -> dict[str, Any]:
    """Time `fn()` `repeats` times after `warmup` calls (the first call's time = compile time).

    `block` is applied to the result to wait for asynchronous work (e.g. jax.block_until_ready).
    Returns seconds: first_call_s, raw, median, min, max.
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
        block(fn())
        raw.append(time.perf_counter() - t0)
    return {
        "first_call_s": first,
        "raw_s": raw,
        "median_s": statistics.median(raw),
        "min_s": min(raw),
        "max_s": max(raw),
    }


def print_table(rows: Sequence[dict[str, Any]], columns: Sequence[str], title: str = "") -> str:
    """Print rows as a Markdown table (also returned)."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}" if abs(v) < 1e5 else f"{v:,.0f}"
        return str(v)

    lines = [f"### {title}"] if title else []
    lines.append("| " + " | ".join(columns) + " |")
    lines.append("|" + "|".join("---" for _ in columns) + "|")
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |")
    text = "\n".join(lines)
    print(text, flush=True)
    return text


def write_record(name: str, config: dict[str, Any], results: Any, out_dir: str | Path | None = None) -> Path:
    """Write {machine, config, results} to OUT/name.json and return the path."""
    out = Path(out_dir) if out_dir else DEFAULT_OUT
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.json"
    record = {"benchmark": name, "machine": machine_info(), "config": config, "results": results,
              "time": time.strftime("%Y-%m-%dT%H:%M:%S")}
    path.write_text(json.dumps(record, indent=2, default=float))
    print(f"wrote {path}", flush=True)
    return path
