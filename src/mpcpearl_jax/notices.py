"""The library's one channel for what it tells a user beside its return values: a warning
(`warn`: a removed partial checkpoint, a folder that cannot be locked, a busy machine, a stop
signal being honoured) goes to the `mpcpearl_jax` logger at level WARNING. Nothing below the
command layer prints; the commands (`mpcpearl_jax.cli`) show these records as one line each on
stderr, and a program of your own handles them as it handles any logger's (the standard
`logging` module; unconfigured, Python shows them on stderr)."""

from __future__ import annotations

import logging

LOGGER = logging.getLogger("mpcpearl_jax")


def warn(msg: str) -> None:
    """Report `msg` (one line) through the `mpcpearl_jax` logger."""
    LOGGER.warning(msg)
