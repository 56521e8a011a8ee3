"""What the lab's diagnostics share (`lab.diagnostics.imitation`, `lab.diagnostics.crowd_cause`,
`lab.diagnostics.shield`): their command line (--tiny, --full, --out, --threads), the cores they
use, their table and JSON record (`report`); the sizes, cores, failure line and timing are the
measuring commands' own, shared with the benchmarks (`mpcpearl_jax.cli.harness`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from mpcpearl_jax.cli.harness import (  # noqa: F401 (re-exported: the diagnostics' names)
    SIZES,
    check_threads,
    configure_threads,
    fail,
    size_of,
    timed,
)
from mpcpearl_jax.cli.tables import print_table, write_record  # noqa: F401 (re-exported)
from mpcpearl_jax.training import machine  # noqa: F401 (re-exported)


class DiagnosticParser(argparse.ArgumentParser):
    """An ArgumentParser whose `parse_args` also checks, before the diagnostic runs, the flags
    every diagnostic shares (`check_common`): a wrong value ends it with one line and exit 2."""

    def parse_args(self, args=None, namespace=None):  # type: ignore[override]
        parsed = super().parse_args(args, namespace)
        why = check_common(parsed)
        if why is not None:
            print(f"error: {why}", file=sys.stderr, flush=True)
            raise SystemExit(2)
        return parsed


def check_common(args: argparse.Namespace) -> str | None:
    """The one-line error of a --threads outside 1 to the cores this process may use, or of an
    --out that is not a writable folder (created if missing); None when both are good."""
    from mpcpearl_jax.validate import unwritable_folder

    why = check_threads(args)
    if why is not None:
        return why
    out = getattr(args, "out", None)
    if out is not None:
        why = unwritable_folder(out)
        if why is not None:
            return f"--out {out}: not writable ({why}); choose another --out"
    return None


def record_name(base: str, size: str, **settings: tuple[Any, Any]) -> str:
    """A record's file stem: `base`, then the size when not the default one, then `-KEYVALUE`
    (`-KEY-VALUE` when the value starts with a letter) for each setting given as (value,
    default) whose value is not its default (paths by their folder's name, lists joined by '+',
    a long value by a short hash), so that runs of other sizes or settings write records of
    their own instead of replacing each other's."""
    import hashlib
    import re

    def same(a: Any, b: Any) -> bool:
        if isinstance(a, list | tuple) and isinstance(b, list | tuple):
            return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
        if isinstance(a, Path) and isinstance(b, Path):
            return a.resolve() == b.resolve()
        return a == b

    def text(v: Any) -> str:
        if isinstance(v, list | tuple):
            return "+".join(text(x) for x in v)
        return Path(v).name if isinstance(v, Path) else str(v)

    name = base + ("" if size in ("default", None) else f"-{size}")
    for key, (value, default) in settings.items():
        if not same(value, default):
            part = re.sub(r"[^A-Za-z0-9._+=-]", "-", text(value))
            if len(part) > 40:
                part = hashlib.sha1(part.encode()).hexdigest()[:10]
            sep = "" if part[:1].isdigit() else "-"  # -delay6, -run-NAME
            name += f"-{key.replace('_', '-')}{sep}{part}"
    return name


def common_parser(description: str) -> argparse.ArgumentParser:
    """A diagnostic's parser: its size (--tiny for the tests, --full), --out and --threads,
    checked when parsed (`DiagnosticParser`)."""
    p = DiagnosticParser(description=description)
    size = p.add_mutually_exclusive_group()
    size.add_argument("--tiny", action="store_true", help="a seconds-long check (the tests)")
    size.add_argument("--full", action="store_true", help="every task (slow)")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("."),
        help="folder of the JSON record (default: the current one)",
    )
    p.add_argument(
        "--threads", type=int, help="CPU cores, 1 to all (default: all this process may use)"
    )
    return p


def load_runs(flag: str, runs: list[Path]) -> list[Any]:
    """`load_policy` of each run folder given by `flag` (--run, --runs), checked first: none
    given, a folder that is not there or a run that does not load is one line naming the flag
    and the folder (`fail`), not a traceback."""
    from mpcpearl_jax import load_policy
    from mpcpearl_jax.cli.errors import error_line
    from mpcpearl_jax.errors import CheckpointError, ConfigError

    if not runs:
        fail(f"{flag}: no run folder given (give one or more)")
    for run in runs:
        if not run.is_dir():
            fail(f"{flag} {run}: " + ("not a folder" if run.exists() else "no such folder"))
    policies = []
    for run in runs:
        try:
            policies.append(load_policy(run))
        except (CheckpointError, ConfigError, OSError, ValueError, KeyError) as e:
            fail(f"{flag}: {error_line(e)}")
    return policies


def report(
    name: str,
    title: str,
    rows: list[dict],
    cols: list[str],
    config: dict[str, Any],
    record_rows: list[dict],
    out: Path,
) -> dict[str, Any]:
    """A diagnostic's end: its record written (out/name.json), its table printed; returns
    {"config", "rows"}."""
    write_record(name, config, record_rows, out)  # before the table: a broken stdout loses none
    print_table(rows, cols, title)
    return {"config": config, "rows": record_rows}
