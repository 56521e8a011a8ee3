"""Evaluate a trained run (or the GP-MPC baseline) on chosen tasks: `python -m
experiments.evaluate RUN [--split ...]` (the command, `mpcpearl_jax.cli.evaluate`; its `--help`
and module doc list the options)."""

import sys

from mpcpearl_jax.cli.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
