"""The platform a command asks JAX for (`JAX_PLATFORMS`), checked where the command starts: a
platform this machine does not have (`cuda` or `gpu` without a GPU or JAX's CUDA plugin, a
misspelt name) is one line saying so and how to fix it, not the traceback of JAX's backend
start."""

from __future__ import annotations

import os
import re


class PlatformError(ValueError):
    """JAX_PLATFORMS names a platform this machine does not have."""


def requested_platforms() -> str:
    """The platforms asked for: jax's `jax_platforms` setting (read from JAX_PLATFORMS when jax
    is imported), or the variable itself; '' when JAX chooses."""
    import jax

    return (jax.config.jax_platforms or os.environ.get("JAX_PLATFORMS", "") or "").strip()


def check_platform() -> None:
    """Start JAX's backend when JAX_PLATFORMS names a platform other than the CPU and raise
    PlatformError (one line) when it cannot start. Nothing is started when JAX chooses itself or
    only the CPU is asked for (it always exists): call it after the settings that must come
    before JAX starts (threads, `jax.distributed`)."""
    asked = requested_platforms()
    names = [p.strip() for p in asked.split(",") if p.strip()]
    if all(p == "cpu" for p in names):
        return
    import jax

    try:
        jax.devices()
    except (RuntimeError, AssertionError) as e:  # jax: RuntimeError, or a bare assert (cuda)
        known = re.search(r"known backends: \[([^\]]*)\]", str(e))
        why = f" (JAX here knows: {known.group(1).replace(chr(39), '')})" if known else ""
        raise PlatformError(
            f"JAX_PLATFORMS={asked}: not available on this machine{why}; unset JAX_PLATFORMS "
            "(or set JAX_PLATFORMS=cpu) to run on what it has, or install JAX for that "
            "accelerator (e.g. pip install -U 'jax[cuda12]' on a machine with an NVIDIA GPU)"
        ) from None
