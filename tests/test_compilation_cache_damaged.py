"""A damaged entry of the commands' compilation cache (`mpcpearl_jax.compilation_cache`): a file
cut short by a full disk (empty, or truncated) under its final name. The first process that
meets it removes it with one warning line naming it, compiles the program and writes the entry
anew; later processes read it back, silently."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
import zlib
from pathlib import Path

import pytest

from mpcpearl_jax import compilation_cache as cc

ROOT = Path(__file__).resolve().parents[1]

# Two programs that compile well over the cache's threshold (every program is written here:
# the threshold is set to 0 after `enable`), their entries and this process's cache hits.
_PROGRAM = """
import json
import jax, jax.numpy as jnp
from mpcpearl_jax import compilation_cache as cc
from mpcpearl_jax.notices import LOGGER
import logging, sys
LOGGER.addHandler(logging.StreamHandler(sys.stderr))
hits = []
jax.monitoring.register_event_listener(
    lambda name, **kw: hits.append(name) if name == "/jax/compilation_cache/cache_hits" else None
)
folder = cc.enable()
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
def f(x):
    for i in range(60):
        x = jnp.sin(x * (i + 1.0)) + jnp.cos(x[::-1] - i) * 1e-3
    return x
def g(x):
    for i in range(60):
        x = jnp.sin(x * (i + 2.0)) + jnp.cos(x[::-1] + i) * 1e-3
    return x
x = jnp.linspace(0.0, 1.0, 32)
total = float(jax.jit(f)(x).sum()) + float(jax.jit(g)(x).sum())
ours = [p for p in folder.iterdir() if p.name.startswith(("jit_f-", "jit_g-"))]
sizes = {p.name: p.stat().st_size for p in ours}
print(json.dumps({"sum": total, "sizes": sizes, "hits": len(hits)}))
"""


def _run(cache: Path) -> tuple[dict, str]:
    env = {k: v for k, v in os.environ.items() if k != cc.ENV}
    env[cc.ENV] = str(cache)
    out = subprocess.run(
        [sys.executable, "-c", _PROGRAM], env=env, cwd=ROOT, capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout), out.stderr


# three processes importing JAX: ~95 s on the loaded 2-core CPU; the fast sibling is
# test_a_failed_read_removes_the_entry_with_one_line (the same guard, in this process)
@pytest.mark.slow
def test_a_damaged_entry_is_removed_with_one_line_and_written_anew(tmp_path):
    cache = tmp_path / "cache"
    first, _ = _run(cache)
    assert len(first["sizes"]) == 2 and all(first["sizes"].values())
    f_entry, g_entry = (cache / name for name in sorted(first["sizes"]))
    f_entry.write_bytes(b"")  # a full disk: an empty file, and one cut short
    g_entry.write_bytes(g_entry.read_bytes()[: g_entry.stat().st_size // 2])
    second, err = _run(cache)
    lines = err.strip().splitlines()
    assert len(lines) == 2, err  # one line per damaged entry, no traceback, no JAX warning
    for entry in (f_entry, g_entry):
        (line,) = [x for x in lines if str(entry) in x]
        assert line.startswith("warning: removed a damaged compilation cache entry"), line
        assert f"{cc.ENV}=off" in line
    assert second["sizes"] == first["sizes"]  # compiled again and written anew, whole
    assert second["sum"] == first["sum"]
    third, err = _run(cache)  # read back from now on, silently
    assert err == "" and third["hits"] >= 2 and third["sum"] == first["sum"]


def test_a_failed_read_removes_the_entry_with_one_line(monkeypatch, caplog):
    """JAX's read of an entry (`get_executable_and_time`) failing on a truncated file: with the
    guard `enable` installs, the entry is removed (so that JAX writes it anew) and the read is a
    miss, with one line naming the entry; JAX's own verification error still propagates."""
    import jax
    from jax._src import compilation_cache as jcc

    key = f"jit_damaged-{uuid.uuid4().hex}"
    entry = Path(jax.config.jax_compilation_cache_dir) / f"{key}-cache"
    entry.write_bytes(b"x\x9c\x01")

    def read(cache_key, *args, **kwargs):
        raise zlib.error("Error -5 while decompressing data: incomplete or truncated stream")

    monkeypatch.setattr(jcc, "get_executable_and_time", read)
    cc._guard_reads()
    with caplog.at_level("WARNING", logger="mpcpearl_jax"):
        assert jcc.get_executable_and_time(key, None, None) == (None, None)
    assert not entry.exists()
    (line,) = [r.getMessage() for r in caplog.records]
    assert line.startswith("warning: removed a damaged compilation cache entry")
    assert str(entry) in line and "truncated stream" in line and f"{cc.ENV}=off" in line
    cc._guard_reads()  # once only
    assert not hasattr(jcc.get_executable_and_time.__wrapped__, "__wrapped__")
    if hasattr(jcc, "CacheVerificationError"):

        def verify(cache_key, *args, **kwargs):
            error = jcc.CacheVerificationError
            raise error.__new__(error)

        monkeypatch.setattr(jcc, "get_executable_and_time", verify)
        cc._guard_reads()
        with pytest.raises(jcc.CacheVerificationError):
            jcc.get_executable_and_time(key, None, None)


def test_an_entry_that_cannot_be_removed_is_one_line_naming_it(tmp_path, monkeypatch, caplog):
    """A damaged entry in a folder where it cannot be removed: one line naming the entry and the
    way out (delete it, or the cache off); the program is compiled (JAX's "not cached")."""

    def refuse(self, missing_ok=False):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Path, "unlink", refuse)
    with caplog.at_level("WARNING", logger="mpcpearl_jax"):
        assert cc._damaged("jit_h-abc", ValueError("truncated\nsecond line")) == (None, None)
    (line,) = [r.getMessage() for r in caplog.records]
    assert "jit_h-abc-cache" in line and "delete it" in line and f"{cc.ENV}=off" in line
    assert "ValueError: truncated" in line and "\n" not in line
