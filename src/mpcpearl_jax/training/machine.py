"""The machine a run or benchmark ran on (recorded in every curve and benchmark record), a
Markdown table's text (`format_table`; the commands print it, `mpcpearl_jax.cli.tables`), the
cores a benchmark or diagnostic process uses (`configure_threads`) and its JSON record
(`write_record`)."""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def machine_info() -> dict[str, Any]:
    """CPU, thread and library versions of this run."""
    info: dict[str, Any] = {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
        "cores_available": available_cores(),
        "processor": platform.processor() or platform.machine(),
        "loadavg_1m_5m_15m": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
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
        if mod == "torch" and "torch" not in sys.modules:
            continue  # do not import torch just to print its version
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


def format_table(rows: Sequence[dict[str, Any]], columns: Sequence[str], title: str = "") -> str:
    """Rows as a Markdown table's text (`### title` above it when given)."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}" if abs(v) < 1e5 else f"{v:,.0f}"
        return str(v)

    lines = [f"### {title}"] if title else []
    lines.append("| " + " | ".join(columns) + " |")
    lines.append("|" + "|".join("---" for _ in columns) + "|")
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |")
    return "\n".join(lines)


def configure_threads(n: int | None) -> dict[str, Any]:
    """Give JAX (XLA) and PyTorch the same `n` CPU cores; returns what was set, for the record.

    The process is pinned to `n` cores (XLA sizes its intra-op pool from the schedulable cores);
    with n == 1 XLA's multi-threaded Eigen is also switched off. PyTorch gets
    `set_num_threads(n)` when it is imported later through `torch_threads`.
    """
    if n is not None and n < 1:  # -1 pinned all cores but the last; 0 meant all of them
        raise ValueError(f"threads {n}: must be at least 1 (None: all cores)")
    n = n or available_cores()
    info: dict[str, Any] = {"threads": n}
    if hasattr(os, "getloadavg"):  # other work on the machine skews every timing: record it
        info["loadavg_at_start_1m_5m_15m"] = list(os.getloadavg())
    jax_started = "jax" in sys.modules
    if hasattr(os, "sched_setaffinity"):
        cores = sorted(os.sched_getaffinity(0))
        if n > len(cores):
            raise ValueError(f"--threads {n} but only {len(cores)} cores are available")
        os.sched_setaffinity(0, cores[:n])
        info["affinity"] = cores[:n]
    if n == 1:
        flags = os.environ.get("XLA_FLAGS", "")
        extra = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
        os.environ["XLA_FLAGS"] = (flags + " " + extra).strip()
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(n)
    info["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    if jax_started:
        info["note"] = "jax was imported before configure_threads; XLA flags may not apply"
    return info


def write_record(name: str, config: dict[str, Any], results: Any, out_dir: str | Path) -> Path:
    """Write {machine, config, results} of a benchmark or diagnostic to out_dir/name.json and
    return the path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.json"
    record = {
        "benchmark": name,
        "machine": machine_info(),
        "config": config,
        "results": results,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    path.write_text(json.dumps(record, indent=2, default=_jsonable))
    return path


def _jsonable(x: Any) -> Any:
    try:
        return float(x)
    except (TypeError, ValueError):
        return str(x)
