"""Benchmarks: every speed claim of the project, measured side by side. See benchmarks/README.md."""

from mpcpearl_jax.cli.stopping import guard_program

guard_program()  # a stop signal in a benchmark: one line, exit 128 + the signal
