"""Benchmarks: every speed claim of the project, measured side by side. See benchmarks/README.md."""

import os

# The benchmarks time compilations too (compile_s, first iterations): they compile afresh, not
# from the commands' persistent compilation cache, unless MPCPEARL_JAX_CACHE names a folder
# (`mpcpearl_jax.compilation_cache`; benchmarks.compile_cache sets its own)
os.environ.setdefault("MPCPEARL_JAX_CACHE", "off")

from mpcpearl_jax.cli.stopping import guard_program  # noqa: E402

guard_program()  # a stop signal in a benchmark: one line, exit 128 + the signal
