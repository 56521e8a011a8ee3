"""Memory estimates before allocation: a size field too large for the machine is a one-line
`ConfigError` naming the fields to lower, before anything is allocated or written, not an XLA
out-of-memory traceback after the run folder was set up.

The trainers measure their state exactly (`jax.eval_shape` of the initial state: shapes only, no
computation) and compare it with the memory free on the devices (host memory for the CPU).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import jax

from mpcpearl_jax.errors import ConfigError


def tree_bytes(tree: Any) -> int:
    """Bytes of every array (or `jax.ShapeDtypeStruct`) leaf of `tree`."""
    leaves = jax.tree_util.tree_leaves(tree)
    return sum(math.prod(x.shape) * x.dtype.itemsize for x in leaves if hasattr(x, "dtype"))


def free_bytes() -> int | None:
    """Memory free for this process's arrays: on accelerators the devices' limit less what is in
    use (summed over the local devices), on the CPU the host's available memory; None when
    unknown."""
    devices = jax.local_devices()
    if devices[0].platform != "cpu":
        total = 0
        for d in devices:
            stats = d.memory_stats() or {}
            if "bytes_limit" not in stats:
                return None
            total += stats["bytes_limit"] - stats.get("bytes_in_use", 0)
        return total
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _size(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def check_fits(nbytes: int, what: str, fields: str, free: int | None = None) -> None:
    """ConfigError naming `fields` when `nbytes` (this process's share of `what`) exceed the free
    memory (`free_bytes()` unless given)."""
    free = free_bytes() if free is None else free
    if free is not None and nbytes > free:
        raise ConfigError(
            f"{fields}: {what} would need {_size(nbytes)} of memory, {_size(free)} are free on "
            "this machine; lower them"
        )


def check_state_fits(
    init_state: Any, what: str, fields: str | Callable[[Any], tuple[str, str]]
) -> None:
    """`check_fits` for the value `init_state()` would build, measured with `jax.eval_shape`; with
    several processes each holds its share. `fields` may be a function of the state's shapes
    returning (fields, what), called only when the state does not fit: it names what grew."""
    shapes = jax.eval_shape(init_state)
    nbytes = tree_bytes(shapes) // jax.process_count()
    free = free_bytes()
    if callable(fields) and free is not None and nbytes > free:
        fields, what = fields(shapes)
    check_fits(nbytes, what, str(fields), free)


def grown_fields(values: Mapping[str, Any], defaults: Mapping[str, Any], prefix: str) -> list[str]:
    """The size fields of `values` (integers, or tuples of integers such as layer widths) larger
    than in `defaults` (a tuple: more entries or a larger sum), as "prefix.name=value"."""
    out = []
    for name, v in values.items():
        d = defaults.get(name)
        if isinstance(v, bool) or isinstance(d, bool) or d is None:
            continue
        if isinstance(v, int) and isinstance(d, int):
            grew = v > d
        elif isinstance(v, (tuple, list)) and isinstance(d, (tuple, list)):
            ints = all(isinstance(x, int) for x in (*v, *d))
            grew = ints and (len(v) > len(d) or sum(v) > sum(d))
        else:
            continue
        if grew:
            shown = ",".join(map(str, v)) if isinstance(v, (tuple, list)) else v
            out.append(f"{prefix}.{name}={shown}")
    return out


def dataclass_defaults(cls: type) -> dict[str, Any]:
    """A dataclass's field defaults (fields without one left out)."""
    out = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out
