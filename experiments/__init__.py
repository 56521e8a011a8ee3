"""The commands: `python -m experiments.MODULE` (README.md, docs/usage.md)."""

from mpcpearl_jax.cli.stopping import guard_program

guard_program()  # a stop signal during a command's imports: one line, exit 128 + the signal
