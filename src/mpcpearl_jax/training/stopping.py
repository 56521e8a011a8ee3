"""The library's half of stopping a run the ways a user stops it: Ctrl-C (SIGINT, which a
terminal sends to its whole process group), SIGTERM (`kill`, `timeout`, a scheduler) and SIGHUP
(a closed terminal).

While `Session.train` trains with `handle_sigint`, `stop_flag` holds these signals: the first
one asks the loop to save and stop (`loop.train_loop`), a second one raises KeyboardInterrupt at
once. Every signal received is recorded (`received`), for the exit code a command chooses. The
MPC's worker processes leave the process group and ignore these signals
(`mpc.pool.pool_worker_init`): the training process ends them. The commands' half (every stop
signal as KeyboardInterrupt for a command's whole life, its one line and exit code) is
`mpcpearl_jax.cli.stopping`.

Where a signal raises, it raises through `interrupt`. JAX's compiler call
(`backend_compile_and_load`) checks for signals while XLA compiles in a thread of its own: a
KeyboardInterrupt raised there returns at once, and the compilation goes on in that thread.
`interrupt` records it (`compile_abandoned`), and a command then ends without the interpreter's
teardown, which, run under the live compilation, crashed the process (a segmentation fault in
that thread) after its last line. A KeyboardInterrupt raised inside JAX's garbage-collection
callback would be swallowed there ("Exception ignored"): `interrupt` sends the signal again
instead, to be raised at the next line.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from typing import Any

from mpcpearl_jax.notices import warn
from mpcpearl_jax.training.loop import Progress

# the signals a user stops a run with: Ctrl-C (SIGINT, to the terminal's whole process group), a
# scheduler's or `kill`'s SIGTERM, a closed terminal's SIGHUP
STOP_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)
)
received: list[int] = []  # the stop signals received (cleared when a command starts)
# a stop signal raised KeyboardInterrupt inside JAX's compiler call: XLA goes on compiling
compile_abandoned: list[bool] = []


class StopNow(KeyboardInterrupt):
    """The first stop signal, raised inside a JAX compilation when stopping there loses no
    finished iteration (`stop_flag`): the stop takes effect at once instead of after the
    compilation (seconds to minutes)."""


def in_compile(frame) -> bool:
    """Whether a signal handler's `frame` is JAX's call into XLA's compiler (where a
    KeyboardInterrupt returns at once and leaves the compilation running)."""
    code = getattr(frame, "f_code", None)
    return (
        code is not None
        and code.co_name == "backend_compile_and_load"
        and code.co_filename.endswith(os.path.join("jax", "_src", "compiler.py"))
    )


def interrupt(signum: int, frame, exc: type[KeyboardInterrupt] = KeyboardInterrupt) -> None:
    """Raise `exc` from a stop signal's handler (module doc): recorded in `compile_abandoned`
    where it leaves a compilation running; inside JAX's garbage-collection callback, which would
    swallow it, the signal is sent to the main thread again (it raises at the next line)."""
    if getattr(getattr(frame, "f_code", None), "co_name", "") == "_xla_gc_callback":
        main = threading.main_thread().ident
        threading.Timer(0.01, signal.pthread_kill, (main, signum)).start()
        return
    if in_compile(frame):
        compile_abandoned.append(True)
    raise exc


def signal_name(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


def install(handler) -> dict[int, Any]:
    """Install `handler` for every stop signal (main thread only); -> the old handlers."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {s: signal.signal(s, handler) for s in STOP_SIGNALS}


def restore(old: dict[int, Any]) -> None:
    for s, handler in old.items():
        signal.signal(s, handler)


class StopFlag:
    """What `stop_flag` yields: call it for whether a stop was asked; `asked` says whether a
    stop signal arrived at any time while the flag was held."""

    def __init__(self) -> None:
        self.asked = False

    def __call__(self) -> bool:
        return self.asked


@contextlib.contextmanager
def stop_flag(enabled: bool, where: Progress):
    """A stop flag set by the first stop signal (Ctrl-C, SIGTERM, SIGHUP): the loop saves and
    stops (`loop.train_loop`); a second one raises KeyboardInterrupt at once. The first signal
    is reported (`notices.warn`): what is saved, and what a second signal does. Where no
    finished iteration is unsaved, a first signal during a JAX compilation, or one that came
    before a compilation that then starts, raises `StopNow` in it (compiling the first
    iteration's programs takes a minute or more, and the flag is read only between phases)."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield None
        return
    flag = StopFlag()
    main = threading.main_thread().ident
    resent = [0]  # signals `watch` sent, not yet handled
    done = threading.Event()  # the flag is released, or the stop raised

    def nothing_unsaved() -> bool:
        return where.iterations == max(where.saved, 0)

    def watch(signum: int) -> None:
        """After a first stop with nothing unsaved that came outside a compilation: once the
        main thread is in one (a compilation that started after the signal), the signal is sent
        to it again, so that the compilation is stopped too."""
        while not done.wait(0.2):
            if not nothing_unsaved():
                return
            if in_compile(sys._current_frames().get(main)):
                resent[0] += 1
                signal.pthread_kill(main, signum)
                done.wait(1.0)  # the handler's turn

    def handler(signum, frame):
        if resent[0]:  # sent again by `watch`
            resent[0] -= 1
            if nothing_unsaved() and in_compile(frame):
                done.set()
                interrupt(signum, frame, StopNow)
            return
        received.append(signum)
        if flag.asked:
            done.set()
            interrupt(signum, frame)
            return
        flag.asked = True
        name = signal_name(signum)
        if nothing_unsaved():  # nothing unsaved: at the next boundary
            warn(f"\n{name}: stopping at the next phase boundary ({name} again: at once)")
            if in_compile(frame):
                done.set()
                interrupt(signum, frame, StopNow)
            threading.Thread(target=watch, args=(signum,), daemon=True, name="stop-watch").start()
            return
        back = f"iteration {where.saved}" if where.saved >= 0 else "the start"
        warn(
            f"\n{name}: saving and stopping, at the latest after iteration "
            f"{where.iterations + 1} ({name} again: stop at once, back to {back})"
        )

    old = install(handler)
    try:
        yield flag
    finally:
        done.set()
        restore(old)
