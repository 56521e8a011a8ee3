"""Test configuration: a persistent XLA compilation cache shared by the test session, its
worker processes and the commands the tests start, so that identical programs (e.g. trainers
rebuilt from the same config) compile once; LLVM optimisation level 1 for the compiled
programs; the number of worker processes for `-n auto`; the fault tests' reference run (`ref0`),
trained once per worker process that needs it."""

import os
import tempfile
from pathlib import Path

# Most of the suite's time is XLA compiling small programs that then run for milliseconds. The
# CPU backend's LLVM level 1 (XLA's default is 2) compiles them faster; it changes no operation,
# only how the machine code is optimised, so values agree to the rounding the tests already
# allow across CPUs (tests/test_fingerprint.py holds at 1e-4 either way). The test processes
# inherit it (set before JAX starts its backend); MPCPEARL_TEST_XLA_OPT=2 runs the suite at
# XLA's default, "keep" leaves XLA_FLAGS as the environment has it.
_OPT = os.environ.get("MPCPEARL_TEST_XLA_OPT", "1")
if _OPT != "keep" and "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + f" --xla_backend_optimization_level={_OPT}"
    ).strip()

import pytest  # noqa: E402

from mpcpearl_jax import compilation_cache  # noqa: E402

# One cache for the test session, its worker processes and the commands the tests start (they
# inherit MPCPEARL_JAX_CACHE, which `compilation_cache.enable` reads where a command starts):
# never the user's own cache folder
_CACHE = os.environ.get("MPCPEARL_TEST_JAX_CACHE") or os.path.join(
    tempfile.gettempdir(), "mpcpearl_jax_test_xla_cache"
)
os.environ[compilation_cache.ENV] = _CACHE
compilation_cache.enable()

import mpcpearl_jax.cli  # noqa: E402

# the library's notices (`mpcpearl_jax.notices`) as the commands show them: one line each on
# stderr, whether a test calls a command or the library
mpcpearl_jax.cli.setup()


def pytest_xdist_auto_num_workers(config) -> int:
    """`-n auto` (the default in pyproject.toml): one test process per core, at most 4; each
    process holds its own compiled programs (a few GiB by the end of the suite)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, 4))


@pytest.fixture(scope="session")
def ref0(tmp_path_factory) -> Path:
    """The uninterrupted eps-0 run of the fault tests' small configuration (`faults_helpers`),
    trained in this process once per session: tests/test_faults_*.py only read it or copy it."""
    from faults_helpers import small_cfg, train_only

    out = tmp_path_factory.mktemp("ref") / "eps0"
    train_only(small_cfg(0.0), out)
    return out
