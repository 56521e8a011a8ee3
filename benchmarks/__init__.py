"""Benchmarks: every speed claim of the project, measured side by side. See benchmarks/README.md."""

import os

from mpcpearl_jax import cli, compilation_cache
from mpcpearl_jax.cli.stopping import guard_program

# The benchmarks time compilations too (compile_s, first iterations): they compile afresh, not
# from the commands' persistent compilation cache, unless MPCPEARL_JAX_CACHE names a folder
# (`mpcpearl_jax.compilation_cache`; benchmarks.compile_cache sets its own)
cli.setup(cache=compilation_cache.ENV in os.environ)
guard_program()  # a stop signal in a benchmark: one line, exit 128 + the signal
