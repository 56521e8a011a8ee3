"""JAX's persistent compilation cache for the commands: a program compiled once on a machine is
read back from disk by every later process that compiles the same program (same JAX and XLA
versions, flags and device), instead of being compiled again.

Every command calls `enable()` where it starts (`mpcpearl_jax.cli.setup`). The folder:

- `MPCPEARL_JAX_CACHE=off` (or `0`, `false`, `no`, `none`): no cache from this package (a cache
  the user set up for JAX itself, e.g. with `JAX_COMPILATION_CACHE_DIR`, stays as it is);
- `MPCPEARL_JAX_CACHE=/some/folder`: that folder;
- else a folder JAX was already given (`JAX_COMPILATION_CACHE_DIR`, `jax_compilation_cache_dir`);
- else `$XDG_CACHE_HOME/mpcpearl_jax/jax`, or `~/.cache/mpcpearl_jax/jax` without
  `XDG_CACHE_HOME`.

A folder that cannot be made or written to leaves the cache off, with one warning
(`mpcpearl_jax.notices`: a line on stderr in the commands); the command runs as without a
cache. Entries are never evicted: the folder grows by a
few MB per configuration trained (the programs of one shape), and deleting it is always safe
(the next command compiles again). An entry that cannot be read back (a file cut short by a full
disk) is removed when a command meets it, with one warning line naming it; its program is
compiled again and written anew.
"""

from __future__ import annotations

import functools
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

from mpcpearl_jax.notices import warn

ENV = "MPCPEARL_JAX_CACHE"
OFF = ("off", "0", "false", "no", "none")
SUBDIR = Path("mpcpearl_jax") / "jax"
# Programs that took less than this to compile are not written: a cache read (a file, its
# decompression and deserialization) costs milliseconds, so caching a program that compiles in a
# few milliseconds gains nothing and fills the folder with thousands of entries (the eager
# operations). Most of a training command's compile time is in programs of 0.1-10 s: the
# collection's rollouts, the gradient steps and the evaluation (benchmarks/README.md,
# `compile_cache`).
MIN_COMPILE_TIME_S = 0.1
MIN_ENTRY_SIZE_BYTES = 0  # every size: a small program that compiled slowly is worth its entry


def cache_dir(environ: Mapping[str, str] | None = None, jax_dir: str | None = None) -> Path | None:
    """The folder `enable` uses, or None where the cache is off (module doc): from the
    environment `environ` (default: this process's) and the folder JAX was already given
    (`jax_dir`), without touching the disk."""
    env = os.environ if environ is None else environ
    value = env.get(ENV, "").strip()
    if value.lower() in OFF:
        return None
    if value:
        return Path(value).expanduser()
    if jax_dir:
        return Path(jax_dir).expanduser()
    base = env.get("XDG_CACHE_HOME", "").strip()
    # the XDG base directory spec: a relative XDG_CACHE_HOME is invalid and is ignored
    root = Path(base) if base and os.path.isabs(base) else Path.home() / ".cache"
    return root / SUBDIR


def writable(folder: Path) -> str | None:
    """None where `folder` exists (made with its parents if need be) and a file can be written
    in it, else why not (one line)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
            pass
    except OSError as e:
        return f"{type(e).__name__}: {e.strerror or e}"
    return None


def enable(environ: Mapping[str, str] | None = None) -> Path | None:
    """Turn JAX's persistent compilation cache on in this process, in the folder `cache_dir`
    names; returns it, or None where the cache stays off (switched off, or the folder cannot be
    written: one notice, `mpcpearl_jax.notices`). Reports nothing otherwise; call it before the
    programs it should keep are compiled (it starts no backend). Calling it again with the same
    folder does nothing; with another folder, the cache moves there."""
    import jax

    current = jax.config.jax_compilation_cache_dir
    folder = cache_dir(environ, current)
    if folder is None:
        return None
    why = writable(folder)
    if why is not None:
        warn(
            f"warning: the compilation cache is off: cannot write to {folder} ({why}); set "
            f"{ENV} to a writable folder, or {ENV}=off"
        )
        return None
    if current != str(folder):
        jax.config.update("jax_compilation_cache_dir", str(folder))
        # JAX opens its cache at the first compile after a folder is set and keeps it: point
        # it at the new folder where one was opened before
        from jax.experimental.compilation_cache import compilation_cache as cc

        cc.reset_cache()
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", MIN_ENTRY_SIZE_BYTES)
    _guard_reads()
    return folder


ENTRY_SUFFIX = "-cache"  # JAX's file name of an entry: <key>-cache


def _guard_reads() -> None:
    """Wrap JAX's read of a cache entry (`jax._src.compilation_cache.get_executable_and_time`)
    so that an entry that cannot be read back is removed, with one warning naming it: JAX itself
    warns (two lines) and compiles the program again at every later read, and never replaces
    the entry (it writes only where no file of that name is). Nothing where this JAX has no such
    function; idempotent."""
    try:
        from jax._src import compilation_cache as jcc
    except ImportError:  # pragma: no cover - another JAX layout: its own behaviour
        return
    read = getattr(jcc, "get_executable_and_time", None)
    if read is None or getattr(read, "_mpcpearl_guarded", False):
        return
    keep = getattr(jcc, "CacheVerificationError", None)  # JAX raises it on purpose

    @functools.wraps(read)
    def guarded(cache_key, *args, **kwargs):
        try:
            return read(cache_key, *args, **kwargs)
        except Exception as e:
            if keep is not None and isinstance(e, keep):
                raise
            return _damaged(cache_key, e)

    guarded._mpcpearl_guarded = True  # type: ignore[attr-defined]
    jcc.get_executable_and_time = guarded


def _damaged(cache_key: str, error: Exception) -> tuple[None, None]:
    """The entry of `cache_key` could not be read (`error`): remove it (its program is compiled
    and written again), one warning line; -> JAX's "not in the cache"."""
    import jax

    folder = jax.config.jax_compilation_cache_dir
    if not folder:  # pragma: no cover - read from a cache with no folder: JAX's own handling
        raise error
    entry = Path(folder).expanduser() / f"{cache_key}{ENTRY_SUFFIX}"
    why = f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}".rstrip()
    try:
        entry.unlink(missing_ok=True)
    except OSError as e:
        warn(
            f"warning: the compilation cache entry {entry} cannot be read ({why}) nor removed "
            f"({e.strerror or e}): delete it, or set {ENV}=off; its program is compiled again"
        )
        return None, None
    warn(
        f"warning: removed a damaged compilation cache entry, {entry} ({why}); its program is "
        f"compiled again and written anew ({ENV}=off: no cache)"
    )
    return None, None
