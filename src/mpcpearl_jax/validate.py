"""One validation helper for every configuration dataclass (`NavConfig`, `PearlConfig`,
`MPCConfig`, `TrainConfig`, `ExperimentConfig`, the GrBAL configs).

Each check reads fields of a config object and raises `ConfigError("Class.field: what is wrong,
got value")`, so every message names the field the user has to change. Booleans are never
accepted as numbers, and numbers must be finite.
"""

from __future__ import annotations

import math
import re
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NoReturn

from mpcpearl_jax.errors import ConfigError


def fail(obj: Any, field: str, msg: str) -> NoReturn:
    raise ConfigError(f"{type(obj).__name__}.{field}: {msg}")


def check(ok: bool, obj: Any, field: str, msg: str) -> None:
    if not ok:
        fail(obj, field, msg)


def is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def ints(obj: Any, *fields: str, lo: int | None = 1) -> None:
    """Each field is an int >= lo (1: a positive int, 0: a non-negative int, None: any int)."""
    what = {1: "a positive int", 0: "a non-negative int", None: "an int"}.get(lo, f"an int >= {lo}")
    for f in fields:
        v = getattr(obj, f)
        check(is_int(v) and (lo is None or v >= lo), obj, f, f"must be {what}, got {v!r}")


def positive(obj: Any, *fields: str, none_ok: bool = False) -> None:
    """Each field is a positive finite number (or None when none_ok)."""
    for f in fields:
        v = getattr(obj, f)
        if not (none_ok and v is None):
            check(is_number(v) and v > 0, obj, f, f"must be a positive finite number, got {v!r}")


def nonnegative(obj: Any, *fields: str, none_ok: bool = False) -> None:
    """Each field is a non-negative finite number (or None when none_ok)."""
    for f in fields:
        v = getattr(obj, f)
        if not (none_ok and v is None):
            ok = is_number(v) and v >= 0
            check(ok, obj, f, f"must be a non-negative finite number, got {v!r}")


def interval(obj: Any, *fields: str, lo: float, hi: float, open_lo: bool = False) -> None:
    """Each field is a finite number in [lo, hi] ((lo, hi] when open_lo)."""
    bound = f"({lo:g}, {hi:g}]" if open_lo else f"[{lo:g}, {hi:g}]"
    for f in fields:
        v = getattr(obj, f)
        ok = is_number(v) and (v > lo if open_lo else v >= lo) and v <= hi
        check(ok, obj, f, f"must lie in {bound}, got {v!r}")


def flags(obj: Any, *fields: str) -> None:
    """Each field is a bool."""
    for f in fields:
        v = getattr(obj, f)
        check(isinstance(v, bool), obj, f, f"must be true or false, got {v!r}")


def _tuple_form(v: Any) -> str:
    """How a tuple of layer sizes is written (in `--set` and the JSON config), for the message
    of a value given as text or a single int: ' (write it as [64,64])'; '' for other values."""
    if is_int(v) and v > 0:
        return f" (write it as [{v}])"
    if not isinstance(v, str):
        return ""
    parts = [p for p in re.split(r"[\s,]+", v.strip().strip("()[]")) if p]
    if parts and all(p.isdigit() for p in parts):
        return f" (write it as [{','.join(parts)}])"
    return " (write it as a list, e.g. [64,64])"


def int_tuples(obj: Any, *fields: str) -> None:
    """Each field is a non-empty tuple of positive ints (layer sizes). A value given as text or a
    single int ('64,64', 64: `--set pearl.hidden=64,64` without the brackets) gets the form it
    takes in the message: '... got '64,64' (write it as [64,64])'."""
    for f in fields:
        v = getattr(obj, f)
        ok = isinstance(v, tuple) and len(v) > 0 and all(is_int(h) and h > 0 for h in v)
        msg = f"must be a non-empty tuple of positive ints, got {v!r}{_tuple_form(v)}"
        check(ok, obj, f, msg)


def one_of(obj: Any, field: str, options: Iterable[Any]) -> None:
    v, options = getattr(obj, field), tuple(options)
    check(v in options, obj, field, f"must be one of {options}, got {v!r}")


def instance(obj: Any, field: str, cls: type | tuple[type, ...], what: str) -> None:
    v = getattr(obj, field)
    check(isinstance(v, cls), obj, field, f"must be {what}, got {type(v).__name__}")


def unwritable_folder(folder) -> str | None:
    """Create `folder` (and its parents) and prove it writable with a probe file that is removed
    again; None if it is, else the cause in a few words (for a one-line error naming it)."""
    try:
        Path(folder).mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-probe-"):
            pass
    except (FileExistsError, NotADirectoryError):
        return "a file is where a folder should be"
    except OSError as e:
        return e.strerror or type(e).__name__
    return None


def not_writable(path, e: OSError) -> str:
    """The one-line error of a folder `path` that `e` kept from being written, with the advice
    its cause calls for."""
    if isinstance(e, (FileExistsError, NotADirectoryError)):
        return f"{path}: not writable (a file is where a folder should be); choose another --out"
    fix = "fix its permissions or " if isinstance(e, PermissionError) else ""
    return f"{path}: not writable ({e.strerror or type(e).__name__}); {fix}choose another --out"


__all__ = [
    "check",
    "fail",
    "flags",
    "instance",
    "int_tuples",
    "interval",
    "ints",
    "is_int",
    "is_number",
    "nonnegative",
    "not_writable",
    "one_of",
    "positive",
    "unwritable_folder",
]
