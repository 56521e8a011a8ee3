"""Stopping a run the ways a user stops it: Ctrl-C (SIGINT, which a terminal sends to its whole
process group), SIGTERM (`kill`, `timeout`, a scheduler) and SIGHUP (a closed terminal).

A command's `main` runs inside `stop_signals_interrupt` (the `stoppable` decorator): every stop
signal raises KeyboardInterrupt, as Ctrl-C does, and is recorded, so the command exits with
`stop_exit_code()` (128 + the signal: 130 for Ctrl-C). While `Session.train` trains, `_stop_flag`
replaces that: the first signal asks the loop to save and stop (`loop.train_loop`), a second
one stops at once. The MPC's worker processes leave the process group and ignore these signals
(`mpc.host.pool_worker_init`): the training process ends them. Outside a command's own handling
(its module imports, a command with none, the interpreter's exit after it returned),
`guard_program` ends the process with one line.
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

from mpcpearl_jax.training.loop import Progress


def _warn(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# the signals a user stops a run with: Ctrl-C (SIGINT, to the terminal's whole process group), a
# scheduler's or `kill`'s SIGTERM, a closed terminal's SIGHUP
STOP_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)
)
_received: list[int] = []  # the stop signals received inside `stop_signals_interrupt`
_finished: list[bool] = []  # a `stoppable` command returned (its output is complete)


def stop_exit_code() -> int:
    """The exit code of a stopped command: 128 + the stop signal it received (130, Ctrl-C's,
    when none was recorded)."""
    return 128 + (_received[-1] if _received else int(signal.SIGINT))


def _signal_name(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


def _install(handler) -> dict[int, Any]:
    """Install `handler` for every stop signal (main thread only); -> the old handlers."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {s: signal.signal(s, handler) for s in STOP_SIGNALS}


def _restore(old: dict[int, Any]) -> None:
    for s, handler in old.items():
        signal.signal(s, handler)


@contextlib.contextmanager
def stop_signals_interrupt():
    """For a command's whole life: every stop signal (SIGINT, SIGTERM, SIGHUP) raises
    KeyboardInterrupt as Ctrl-C does, and is recorded for `stop_exit_code`; inside
    `Session.train` the first one only asks the loop to stop (`stop_flag`)."""
    _received.clear()

    def handler(signum, frame):
        _received.append(signum)
        raise KeyboardInterrupt

    old = _install(handler)
    try:
        yield
    finally:
        _restore(old)


def stoppable(main: Callable[..., int]) -> Callable[..., int]:
    """A command's `main` run inside `stop_signals_interrupt`."""

    @functools.wraps(main)
    def wrapper(*args: Any, **kwargs: Any) -> int:
        with stop_signals_interrupt():
            code = main(*args, **kwargs)
            _finished.append(True)
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
        _received.append(signum)
        done = " after the command finished (its output is complete)" if _finished else ""
        with contextlib.suppress(Exception):  # stdout may be closed, or mid-write
            sys.stdout.flush()
        with contextlib.suppress(Exception):
            print(f"interrupted ({_signal_name(signum)}){done}", file=sys.stderr, flush=True)
        os._exit(128 + signum)

    _install(handler)


@contextlib.contextmanager
def stop_flag(enabled: bool, where: Progress):
    """A stop flag set by the first stop signal (Ctrl-C, SIGTERM, SIGHUP): the loop saves and
    stops (`loop.train_loop`); a second one raises KeyboardInterrupt at once."""
    flag = {"stop": False}
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield None
        return

    def handler(signum, frame):
        _received.append(signum)
        if flag["stop"]:
            raise KeyboardInterrupt
        flag["stop"] = True
        name = _signal_name(signum)
        if where.iterations == max(where.saved, 0):  # nothing unsaved: at the next boundary
            _warn(f"\n{name}: stopping at the next phase boundary ({name} again: at once)")
            return
        back = f"iteration {where.saved}" if where.saved >= 0 else "the start"
        _warn(
            f"\n{name}: saving and stopping, at the latest after iteration "
            f"{where.iterations + 1} ({name} again: stop at once, back to {back})"
        )

    old = _install(handler)
    try:
        yield lambda: flag["stop"]
    finally:
        _restore(old)


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


def exit_interrupted(line: str) -> NoReturn:
    """Print `line` to stderr and end the process with `stop_exit_code()`, without the
    interpreter's teardown: a stop signal can land inside JAX's compiler, which goes on
    compiling, and tearing the runtime down under it crashed the process at exit (a segmentation
    fault after the line). The caller has closed what it opened; MPC pool workers end themselves
    when this process is gone (`mpc.host.watch_parent`)."""
    print(line, file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(stop_exit_code())
