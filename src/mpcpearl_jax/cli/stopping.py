"""The commands' half of stopping (the library's: `mpcpearl_jax.training.stopping`).

A command's `main` runs inside `stop_signals_interrupt` (the `stoppable` decorator): every stop
signal (Ctrl-C, SIGTERM, SIGHUP) raises KeyboardInterrupt, as Ctrl-C does, and is recorded, so
the command exits with `stop_exit_code()` (128 + the signal: 130 for Ctrl-C). While
`Session.train` trains, the library's stop flag replaces that: the first signal asks the loop to
save and stop, a second one stops at once. Outside a command's own handling (its module imports,
a command with none, the interpreter's exit after it returned), `guard_program` ends the process
with one line.
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, NoReturn

from mpcpearl_jax.training.stopping import (
    compile_abandoned,
    install,
    interrupt,
    received,
    restore,
    signal_name,
)

_finished: list[bool] = []  # a `stoppable` command returned (its output is complete)


def stop_exit_code() -> int:
    """The exit code of a stopped command: 128 + the stop signal it received (130, Ctrl-C's,
    when none was recorded)."""
    return 128 + (received[-1] if received else int(signal.SIGINT))


@contextlib.contextmanager
def stop_signals_interrupt():
    """For a command's whole life: every stop signal (SIGINT, SIGTERM, SIGHUP) raises
    KeyboardInterrupt as Ctrl-C does, and is recorded for `stop_exit_code`; inside
    `Session.train` the first one only asks the loop to stop (`training.stopping.stop_flag`)."""
    received.clear()
    compile_abandoned.clear()

    def handler(signum, frame):
        received.append(signum)
        interrupt(signum, frame)

    old = install(handler)
    try:
        yield
    finally:
        restore(old)


def stoppable(main: Callable[..., int]) -> Callable[..., int]:
    """A command's `main` run inside `stop_signals_interrupt`. Where a stop signal left a JAX
    compilation running (`training.stopping.compile_abandoned`), the process ends with main's
    exit code once main has returned (its files closed, its pool shut down), without the
    interpreter's teardown: tearing JAX's runtime down under the compilation crashed the
    process (a segmentation fault in XLA's compiling thread, after the command's last line)."""

    @functools.wraps(main)
    def wrapper(*args: Any, **kwargs: Any) -> int:
        with stop_signals_interrupt():
            code = main(*args, **kwargs)
            _finished.append(True)
        if compile_abandoned:
            _end(code)
        return code

    return wrapper


def guard_program() -> None:
    """Called by a package's `__init__` (experiments, lab, benchmarks): when the process runs
    one of its modules as a program (`python -m PACKAGE.MODULE`, so before the module's own
    imports, seconds of them with JAX), a stop signal that no handler of the command takes ends
    the process at once with one line on stderr and exit code 128 + the signal: during the
    imports, in a command without handling of its own, and in the interpreter's exit after a
    command returned (then the line says its output is complete). No traceback, and no crash of
    JAX's runtime torn down under a compilation. A `stoppable` command's own handling replaces
    it while the command runs."""
    if sys.argv[:1] != ["-m"] or threading.current_thread() is not threading.main_thread():
        return

    def handler(signum, frame):
        received.append(signum)
        done = " after the command finished (its output is complete)" if _finished else ""
        with contextlib.suppress(Exception):  # stdout may be closed, or mid-write
            sys.stdout.flush()
        with contextlib.suppress(Exception):
            print(f"interrupted ({signal_name(signum)}){done}", file=sys.stderr, flush=True)
        os._exit(128 + signum)

    install(handler)


def stops_with(line: str):
    """A command's `main` decorated: run under `stoppable`, a stop signal (Ctrl-C, SIGTERM,
    SIGHUP) ends it with `line` and exit code 128 + the signal (`exit_interrupted`), after the
    `finally` blocks and context managers it was in have run (a child process killed, a pool
    shut down)."""

    def decorate(main):
        @stoppable
        @functools.wraps(main)
        def run(*args, **kwargs):
            try:
                return main(*args, **kwargs)
            except KeyboardInterrupt:
                exit_interrupted(line)

        return run

    return decorate


def _end(code: int) -> NoReturn:
    """End the process with `code` now, its output flushed, without the interpreter's
    teardown."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # closed, or mid-write
            stream.flush()
    os._exit(code)


def exit_interrupted(line: str) -> NoReturn:
    """Print `line` to stderr and end the process with `stop_exit_code()`, without the
    interpreter's teardown: a stop signal can land inside JAX's compiler, which goes on
    compiling, and tearing the runtime down under it crashed the process at exit (a segmentation
    fault after the line). The caller has closed what it opened; MPC pool workers end themselves
    when this process is gone (`mpc.pool.watch_parent`)."""
    print(line, file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(stop_exit_code())
