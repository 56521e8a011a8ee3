"""The commands: `python -m experiments.MODULE` (README.md, docs/usage.md)."""

from mpcpearl_jax import cli
from mpcpearl_jax.cli.stopping import guard_program

cli.setup()  # the library's notices on stderr, the compilation cache (`mpcpearl_jax.cli.setup`)
guard_program()  # a stop signal during a command's imports: one line, exit 128 + the signal
