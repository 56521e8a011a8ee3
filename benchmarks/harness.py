"""Shared helpers for benchmark scripts: threads, timing, machine info, tables and JSON records.

Every script prints a table and writes a JSON record with the machine, versions, config, raw
timings, medians and ratios (measured in the same run). Scripts share the command-line flags of
`common_parser`: `--tiny` (seconds, used by the tests), default (the `benchmarks.all` size),
`--full` (the paper's sizes), `--threads N`, and where the record goes: `--record` (the
committed records, `benchmarks/results/`), `--out DIR`, or by default the git-ignored scratch
folder `benchmarks/results/scratch/`. A `--tiny` run never replaces a committed record.

Call `configure_threads` *before* JAX or PyTorch start their thread pools (i.e. before the first
JAX computation), so that both libraries get the same number of cores.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mpcpearl_jax.cli import tables
from mpcpearl_jax.cli.harness import (  # noqa: F401 (re-exported: the benchmarks' names)
    SIZES,
    calls_for,
    check_platform_or_fail,
    check_threads,
    configure_threads,
    fail,
    size_of,
    summarize,
    time_fn,
    timed,
)
from mpcpearl_jax.cli.tables import print_table  # noqa: F401 (re-exported)
from mpcpearl_jax.training.machine import (  # noqa: F401 (re-exported)
    available_cores,
    machine_info,
)

# the committed records (what the README's speed tables quote) and the git-ignored folder a run
# writes to unless --record or --out says otherwise
RECORDS = Path(__file__).resolve().parent / "results"
SCRATCH = RECORDS / "scratch"
DEFAULT_OUT = SCRATCH


# ------------------------------------------------------------------------------ CLI
class BenchmarkParser(argparse.ArgumentParser):
    """An ArgumentParser whose `parse_args` also checks, before any benchmark runs, what every
    script shares (`check_common`): a wrong value ends the process with one line and exit 2."""

    def parse_args(self, args=None, namespace=None):  # type: ignore[override]
        parsed = super().parse_args(args, namespace)
        why = check_common(parsed)
        if why is not None:
            fail(why)
        return parsed


def error_text(e: BaseException) -> str:
    """An error in one line: an OSError names its file, others their own first line."""
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or type(e).__name__}"
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


def add_out_options(p: argparse.ArgumentParser) -> None:
    """--out DIR and --record (one of them; neither: the scratch folder)."""
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--out",
        default=None,
        help="directory of the JSON record (default: benchmarks/results/scratch/, git-ignored)",
    )
    where.add_argument(
        "--record",
        action="store_true",
        help="write the committed record in benchmarks/results/ (not with --tiny)",
    )


def common_parser(description: str) -> argparse.ArgumentParser:
    """Parser with the flags every benchmark script understands."""
    p = BenchmarkParser(description=description)
    size = p.add_mutually_exclusive_group()
    size.add_argument("--tiny", action="store_true", help="seconds-long smoke run (tests)")
    size.add_argument("--full", action="store_true", help="the paper's sizes (slow)")
    add_out_options(p)
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU cores for JAX and PyTorch alike (default: all cores this process may use)",
    )
    return p


def is_record_folder(folder: str | Path) -> bool:
    """Whether `folder` is the committed records' folder or one inside it (the scratch folder
    and what is under it excepted)."""
    path = Path(folder).resolve()
    inside = path == RECORDS or RECORDS in path.parents
    scratch = path == SCRATCH or SCRATCH in path.parents
    return inside and not scratch


def check_common(args: argparse.Namespace) -> str | None:
    """Check the shared flags of parsed `args` and set `args.out` to the folder of the record
    (--record: benchmarks/results/; --out DIR; else the scratch folder), created and proved
    writable; the one-line error naming the flag, or None."""
    from mpcpearl_jax.validate import unwritable_folder

    why = check_threads(args)
    if why is not None:
        return why
    if getattr(args, "record", False):
        args.out = str(RECORDS)
    elif getattr(args, "out", None) is None:
        args.out = str(SCRATCH)
    if getattr(args, "tiny", False) and is_record_folder(args.out):
        fix = "drop --record" if getattr(args, "record", False) else "choose another --out"
        return (
            f"--tiny is a smoke run and never replaces a measured record in {args.out}: {fix} "
            "(default: benchmarks/results/scratch/, git-ignored)"
        )
    why = unwritable_folder(args.out)
    if why is not None:
        return f"--out {args.out}: not writable ({why}); choose another --out"
    return None


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


# ---------------------------------------------------------------------------- output
def write_record(
    name: str, config: dict[str, Any], results: Any, out_dir: str | Path | None = None
) -> Path:
    """Write {machine, config, results} to OUT/name.json (default the scratch folder,
    benchmarks/results/scratch/) and return the path (`cli.tables.write_record`)."""
    return tables.write_record(name, config, results, out_dir or DEFAULT_OUT)
