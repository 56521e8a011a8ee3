"""What the lab's diagnostics share (`lab.diagnostics.imitation`, `lab.diagnostics.crowd_cause`,
`lab.diagnostics.shield`): their command line (--tiny, --full, --out, --threads), the cores they
use, their table and JSON record (`mpcpearl_jax.training.machine`, `report`), and a one-off
timing."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mpcpearl_jax.cli.platform import PlatformError, check_platform
from mpcpearl_jax.cli.tables import print_table, write_record  # noqa: F401 (re-exported)
from mpcpearl_jax.training import machine

SIZES = ("tiny", "default", "full")


def common_parser(description: str) -> argparse.ArgumentParser:
    """A diagnostic's parser: its size (--tiny for the tests, --full), --out and --threads."""
    p = argparse.ArgumentParser(description=description)
    size = p.add_mutually_exclusive_group()
    size.add_argument("--tiny", action="store_true", help="a seconds-long check (the tests)")
    size.add_argument("--full", action="store_true", help="every task (slow)")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("."),
        help="folder of the JSON record (default: the current one)",
    )
    p.add_argument("--threads", type=int, help="CPU cores (default: all this process may use)")
    return p


def configure_threads(n: int | None) -> dict[str, Any]:
    """`training.machine.configure_threads` (the cores the diagnostic uses), then the platform
    JAX_PLATFORMS asks for, checked: one line and exit 2 if this machine lacks it."""
    info = machine.configure_threads(n)
    try:
        check_platform()
    except PlatformError as e:
        print(f"error: {e}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    return info


def size_of(args: argparse.Namespace) -> str:
    """'tiny', 'default' or 'full' from the parsed flags."""
    return next(s for s, on in (("tiny", args.tiny), ("full", args.full), ("default", True)) if on)


def report(
    name: str,
    title: str,
    rows: list[dict],
    cols: list[str],
    config: dict[str, Any],
    record_rows: list[dict],
    out: Path,
) -> dict[str, Any]:
    """A diagnostic's end: its table printed, its record written (out/name.json); returns
    {"config", "rows"}."""
    print_table(rows, cols, title)
    write_record(name, config, record_rows, out)
    return {"config": config, "rows": record_rows}


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """(fn(), seconds) of one call."""
    start = time.perf_counter()
    return fn(), time.perf_counter() - start
