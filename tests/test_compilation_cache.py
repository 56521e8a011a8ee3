"""The commands' persistent compilation cache (`mpcpearl_jax.compilation_cache`): which folder
(the off switch, a folder given, XDG_CACHE_HOME, ~/.cache), a folder that cannot be written
(one warning line, no cache, the command goes on), the commands started by the tests using the
tests' cache, and a second process reading the programs the first one wrote instead of compiling
them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from mpcpearl_jax import compilation_cache as cc

ROOT = Path(__file__).resolve().parents[1]


def test_the_folder_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    home_cache = tmp_path / "home" / ".cache" / "mpcpearl_jax" / "jax"
    assert cc.cache_dir({}) == home_cache
    assert cc.cache_dir({"XDG_CACHE_HOME": str(tmp_path / "xdg")}) == (
        tmp_path / "xdg" / "mpcpearl_jax" / "jax"
    )
    assert cc.cache_dir({"XDG_CACHE_HOME": "relative/x"}) == home_cache  # invalid: ignored
    for off in ("off", "OFF", "0", "false", "no", "none", " off "):
        assert cc.cache_dir({cc.ENV: off, "XDG_CACHE_HOME": str(tmp_path)}) is None
        assert cc.cache_dir({cc.ENV: off}, jax_dir=str(tmp_path)) is None
    given = tmp_path / "given"
    assert cc.cache_dir({cc.ENV: str(given), "XDG_CACHE_HOME": str(tmp_path)}) == given
    # a folder JAX was already given is kept, unless the variable names another
    assert cc.cache_dir({"XDG_CACHE_HOME": str(tmp_path)}, jax_dir="/j") == Path("/j")
    assert cc.cache_dir({cc.ENV: str(given)}, jax_dir="/j") == given
    assert cc.cache_dir({cc.ENV: ""}, jax_dir=None) == home_cache  # empty: as unset


def test_a_folder_that_cannot_be_written_leaves_the_cache_off_with_one_line(tmp_path, capsys):
    import jax

    before = jax.config.jax_compilation_cache_dir
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert cc.enable({cc.ENV: str(blocker / "cache")}) is None
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("warning: the compilation cache is off")
    assert str(blocker / "cache") in err and f"{cc.ENV}=off" in err
    assert jax.config.jax_compilation_cache_dir == before  # nothing changed
    assert cc.enable({cc.ENV: "off"}) is None and capsys.readouterr().err == ""


def _python(code: str, cache: str | Path | None, **extra: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != cc.ENV}
    env.update(extra)
    if cache is not None:
        env[cc.ENV] = str(cache)
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_commands_started_by_the_tests_use_the_tests_cache(tmp_path):
    """tests/conftest.py exports its cache folder: a command the tests start (a subprocess that
    imports a command package) compiles into it, not into the user's home."""
    import jax

    assert os.environ[cc.ENV] == jax.config.jax_compilation_cache_dir
    code = "import experiments, jax; print(jax.config.jax_compilation_cache_dir)"
    got = _python(code, os.environ[cc.ENV])
    assert got.strip() == os.environ[cc.ENV]
    # and without the variable, the user's folder (here a stand-in XDG_CACHE_HOME)
    xdg = tmp_path / "xdg"
    got = _python(code, None, XDG_CACHE_HOME=str(xdg), JAX_COMPILATION_CACHE_DIR="")
    assert got.strip() == str(xdg / "mpcpearl_jax" / "jax")
    got = _python(code, "off", JAX_COMPILATION_CACHE_DIR="")
    assert got.strip() in ("", "None")  # no folder: no cache


def test_importing_the_command_layer_changes_nothing_until_setup(tmp_path):
    """Importing `mpcpearl_jax.cli` and every module of it installs no log handler and leaves the
    compilation cache off; `cli.setup()` does both."""
    code = (
        "import importlib, pkgutil, jax, mpcpearl_jax.cli as cli\n"
        "from mpcpearl_jax.notices import LOGGER\n"
        "for m in pkgutil.iter_modules(cli.__path__):\n"
        "    importlib.import_module(f'mpcpearl_jax.cli.{m.name}')\n"
        "print(len(LOGGER.handlers), jax.config.jax_compilation_cache_dir)\n"
        "cli.setup()\n"
        "print(len(LOGGER.handlers), jax.config.jax_compilation_cache_dir)\n"
    )
    before, after = _python(code, tmp_path / "cache", JAX_COMPILATION_CACHE_DIR="").splitlines()
    assert before.split() in (["0", "None"], ["0"])  # no handler, no cache folder
    assert after.split() == ["1", str(tmp_path / "cache")]


# A program that takes well over `MIN_COMPILE_TIME_S` to compile on any CPU (hundreds of
# distinct unrolled operations), its result, the cache's entries and its hits in this process.
_PROGRAM = """
import json, time
import jax, jax.numpy as jnp
from mpcpearl_jax import compilation_cache as cc
hits = []
jax.monitoring.register_event_listener(
    lambda name, **kw: hits.append(name) if name == "/jax/compilation_cache/cache_hits" else None
)
folder = cc.enable()
def f(x):
    for i in range(100):
        x = jnp.sin(x * (i + 1.0)) + jnp.cos(x[::-1] - i) * 1e-3
    return x
t0 = time.perf_counter()
y = jax.jit(f)(jnp.linspace(0.0, 1.0, 64)).block_until_ready()
t = time.perf_counter() - t0
# the program's entries (the eager operations' own depend on how fast they compiled)
entries = sorted(p.name for p in folder.iterdir() if p.name.startswith("jit_f-"))
print(json.dumps({"sum": float(y.sum()), "entries": entries, "hits": len(hits), "s": t}))
"""


def test_a_second_process_reads_the_program_the_first_one_compiled(tmp_path):
    cache = tmp_path / "cache"
    first = json.loads(_python(_PROGRAM, cache))
    second = json.loads(_python(_PROGRAM, cache))
    assert first["hits"] == 0 and len(first["entries"]) == 1
    assert second["hits"] >= 1 and second["entries"] == first["entries"]  # read, not written
    assert second["sum"] == first["sum"]
    # switched off: compiled again, the same values, nothing written (the user's folder absent)
    xdg = tmp_path / "xdg"
    code = _PROGRAM.replace("folder.iterdir()", "[]")
    fresh = json.loads(_python(code, "off", XDG_CACHE_HOME=str(xdg), JAX_COMPILATION_CACHE_DIR=""))
    assert fresh["sum"] == first["sum"] and fresh["hits"] == 0 and not xdg.exists()
