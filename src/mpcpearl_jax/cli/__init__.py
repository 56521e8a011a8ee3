"""The command layer, the package's top floor: what every command of experiments/, lab/ and
benchmarks/ shares, and nothing below imports.

- `stopping`: the commands' stop signals (one line, exit code 128 + the signal);
- `errors`: the one error ladder (`one_line_errors`: each error as one line and its exit code);
- `args`: building a config from a command line (the training commands' options, `build_config`,
  `--help-config`);
- `progress`, `tables`: the progress bar, the printed tables, records and lines;
- `output`: a standard output that breaks (`| head`, a full disk) without losing the work;
- `train`: the training commands, one `main` for every registered algorithm
  (`mpcpearl_jax.algorithms`: MPC-PEARL, GrBAL), which parses, calls `mpcpearl_jax.train`,
  prints and chooses the exit code.

`setup()` is where every command starts (the command packages experiments/, lab/ and
benchmarks/ call it on import, the training commands again: it does its work once): the
library's notices (`mpcpearl_jax.notices`) are shown as one line each on stderr, JAX's persistent
compilation cache is on (`mpcpearl_jax.compilation_cache`), and stdout and stderr write what
their encoding lacks as escapes (`\\xa7`) instead of raising (an ASCII locale:
PYTHONIOENCODING=ascii). Importing a module of this package does none of it.
"""

from __future__ import annotations

import logging
import sys


class _StderrLines(logging.Handler):
    """Each record's message as one line on the current sys.stderr, flushed."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            print(record.getMessage(), file=sys.stderr, flush=True)
        except Exception:  # noqa: BLE001 - a closed stderr must not end the command
            self.handleError(record)


_done: list[bool] = []


def tolerant_streams() -> None:
    """stdout and stderr write a character their encoding lacks (the help's "§", a folder's
    name, under an ASCII locale) as a backslash escape instead of raising UnicodeEncodeError."""
    for stream in (sys.stdout, sys.stderr):
        if getattr(stream, "errors", None) == "strict" and hasattr(stream, "reconfigure"):
            try:
                stream.reconfigure(errors="backslashreplace")
            except (OSError, ValueError):  # closed, or not a text stream that can change
                pass


def setup(cache: bool = True) -> None:
    """The commands' start (once per process): the library's notices as lines on stderr, and
    JAX's persistent compilation cache (`mpcpearl_jax.compilation_cache`: MPCPEARL_JAX_CACHE;
    `cache` false: none)."""
    if _done:
        return
    tolerant_streams()
    from mpcpearl_jax import compilation_cache
    from mpcpearl_jax.notices import LOGGER

    LOGGER.addHandler(_StderrLines())
    LOGGER.setLevel(logging.INFO)
    LOGGER.propagate = False
    if cache:
        compilation_cache.enable()  # a folder it cannot write: one notice, no cache
    _done.append(True)
