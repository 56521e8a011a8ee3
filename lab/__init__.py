"""The research harness: screens, campaigns, tables and diagnostics (docs/research-log.md)."""

from mpcpearl_jax.cli.stopping import guard_program

guard_program()  # a stop signal in a lab command: one line, exit 128 + the signal
