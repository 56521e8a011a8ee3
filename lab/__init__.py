"""The research harness: screens, campaigns, tables and diagnostics (docs/research-log.md)."""

from mpcpearl_jax import cli
from mpcpearl_jax.cli.stopping import guard_program

cli.setup()  # the library's notices on stderr, the compilation cache (`mpcpearl_jax.cli.setup`)
guard_program()  # a stop signal in a lab command: one line, exit 128 + the signal
