"""Test configuration: a persistent XLA compilation cache shared by the test session, so that
identical programs (e.g. trainers rebuilt from the same config) compile once."""

import os
import tempfile

import jax

_CACHE = os.environ.get("MPCPEARL_TEST_JAX_CACHE") or os.path.join(
    tempfile.gettempdir(), "mpcpearl_jax_test_xla_cache"
)
jax.config.update("jax_compilation_cache_dir", _CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
