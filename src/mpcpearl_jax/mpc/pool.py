"""The MPC's process pool (method §6): the worker processes that solve a call's fired rows side by
side (`mpc.host.HostSolver`), how many (`pool_size`), how they start (`make_pool`) and end
(`discard_pool`, `watch_parent`), and how a stop signal reaches the training process only
(`pool_worker_init`, `stop_signals_blocked`).

The pool starts its processes by spawn: each one imports the main module again. A script whose
top-level code starts the MPC's pool outside an `if __name__ == "__main__":` block would start it
again in every worker; `make_pool` refuses it with one error naming the guard (`main_unguarded`).
Where the parent cannot see that (the pool started from a thread), a worker that gets there exits
at once with `UNGUARDED_EXIT`, which the parent turns into the same error (`check_started`)
instead of falling back row after row (if the workers get there within `mpc.worker_timeout_s`).
"""

from __future__ import annotations

import ast
import contextlib
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from pathlib import Path
from types import FrameType
from typing import Any, NamedTuple

from mpcpearl_jax.errors import WorkerPoolError

MAX_AUTO_WORKERS = 8  # `mpc.n_workers` 0: one worker per core, at most this many
# the exit status of a worker that met the pool's start while importing the main module again
UNGUARDED_EXIT = 86


def pool_size(n_workers: int, cores: int | None = None) -> int:
    """The worker processes of the MPC's pool for `mpc.n_workers` on `cores` cores (default:
    those this process may use): never more than the cores (a larger pool solves no faster
    and costs a process start and ~200 MB per worker); 0 takes one per core, at most
    `MAX_AUTO_WORKERS`. 1: no pool, the rows are solved in the calling process."""
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not Linux
            cores = os.cpu_count() or 1
    return min(n_workers, cores) if n_workers > 0 else min(cores, MAX_AUTO_WORKERS)


class Stamped(NamedTuple):
    """A pool task's row: its result, the worker's process id, and when the solve started and
    ended (`time.perf_counter`, a clock that all processes of a machine share)."""

    result: Any
    worker: int
    start: float
    end: float


def solve_stamped(solve, *args: Any, **kwargs: Any) -> Stamped:
    """Entry point of a pool task: one row solved by `solve(*args, **kwargs)`
    (`HostSolver.worker_solve`)."""
    start = time.perf_counter()
    res = solve(*args, **kwargs)
    return Stamped(res, os.getpid(), start, time.perf_counter())


def broken(future: Future) -> bool:
    """Whether a finished row's worker was lost (the pool broke under it)."""
    return isinstance(future.exception(), BrokenProcessPool)


# the signals a user stops a training with: Ctrl-C (to the terminal's whole process group), a closed
# terminal, `kill` or a scheduler's SIGTERM (possibly to the whole group)
STOP_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)
)


def pool_worker_init(parent_pid: int) -> None:
    """Pool-worker initializer: the worker leaves the training's process group and ignores
    Ctrl-C and a closed terminal, so a stop signal reaches the training process only, which
    saves and shuts its pool down (a worker killed by the signal would break the pool);
    `watch_parent` ends the worker if the training process is gone. The pool starts its
    workers with the stop signals blocked (`make_pool`), so one sent before this runs waits:
    SIGINT and SIGHUP are then ignored, and a SIGTERM sent to the old group is dropped."""
    with contextlib.suppress(OSError):
        os.setpgid(0, 0)
    for s in STOP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)  # ignoring a blocked, pending signal discards it
    if hasattr(signal, "SIGTERM"):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the pool's own terminate() works
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    watch_parent(parent_pid)


def watch_parent(parent_pid: int, interval_s: float = 2.0) -> None:
    """Pool-worker initializer: exit when the training process is gone (killed with SIGKILL or
    SIGTERM, no chance to shut the pool down), instead of lingering as an orphan."""

    def watch() -> None:
        while True:
            time.sleep(interval_s)
            if os.getppid() != parent_pid:
                os._exit(0)

    threading.Thread(target=watch, daemon=True, name="watch-parent").start()


def guard_message(n_workers: int, where: str) -> str:
    return (
        f"the MPC's worker pool (mpc.n_workers={n_workers}) cannot start: its processes start by "
        f"spawn and import {where} again, whose top-level code starts the MPC again in each of "
        'them. Put that code under `if __name__ == "__main__":`, or set mpc.n_workers=1 to '
        "solve in this process"
    )


def _is_main_test(test: ast.expr) -> bool | None:
    """True for `__name__ == "__main__"`, False for `!=`, None for any other test."""
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1):
        return None
    sides = {ast.dump(test.left), ast.dump(test.comparators[0])}
    if sides != {ast.dump(ast.Name("__name__", ast.Load())), ast.dump(ast.Constant("__main__"))}:
        return None
    return {ast.Eq: True, ast.NotEq: False}.get(type(test.ops[0]))


def _guarded(statements: list[ast.stmt], line: int) -> bool:
    """Whether `line` lies in a block that only `__name__ == "__main__"` enters."""
    for node in statements:
        if not node.lineno <= line <= (node.end_lineno or node.lineno):
            continue
        if isinstance(node, ast.If) and _is_main_test(node.test) is not None:
            inside = node.body if _is_main_test(node.test) else node.orelse
            if any(s.lineno <= line <= (s.end_lineno or s.lineno) for s in inside):
                return True
        blocks = [getattr(node, f, None) for f in ("body", "orelse", "finalbody", "handlers")]
        return any(isinstance(b, list) and _guarded(b, line) for b in blocks)
    return False


def main_unguarded() -> tuple[str, int] | None:
    """(script, line) where this thread runs the main module's top-level code outside an
    `if __name__ == "__main__":` block, which a spawned process runs again; None where it does
    not (or cannot be told: no script file, the main module run by another tool)."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if main is None or not path:
        return None
    frame: FrameType | None = sys._getframe(1)
    while frame is not None and not (
        frame.f_globals is vars(main) and frame.f_code.co_name == "<module>"
    ):
        frame = frame.f_back
    if frame is None:
        return None
    try:
        tree = ast.parse(Path(path).read_text())
    except (OSError, SyntaxError, ValueError, UnicodeDecodeError):
        return None
    return None if _guarded(tree.body, frame.f_lineno) else (str(path), frame.f_lineno)


def make_pool(n_workers: int) -> ProcessPoolExecutor:
    """The MPC's worker pool (spawned processes, `pool_worker_init`). multiprocessing's resource
    tracker, a helper process the pool's queues start, is started here with the stop signals
    blocked: it ignores SIGINT and SIGTERM itself, and a blocked SIGHUP never reaches it, so a
    closed terminal cannot kill it under the training (which then prints tracebacks).

    Raises `WorkerPoolError` where the main script starts the pool from top-level code outside
    `if __name__ == "__main__":` (`main_unguarded`); in a worker importing such a script again,
    exits the worker with `UNGUARDED_EXIT` (`check_started` raises in the parent)."""
    from multiprocessing import resource_tracker

    if getattr(multiprocessing.current_process(), "_inheriting", False):
        os._exit(UNGUARDED_EXIT)  # a spawned process importing the main module: the parent tells
    unguarded = main_unguarded()
    if unguarded is not None:
        raise WorkerPoolError(guard_message(n_workers, f"{unguarded[0]} (line {unguarded[1]})"))
    with stop_signals_blocked():  # ensure_running unblocks SIGINT and SIGTERM when it is done
        resource_tracker.ensure_running()
    with stop_signals_blocked():
        return ProcessPoolExecutor(
            n_workers,
            mp_context=get_context("spawn"),
            initializer=pool_worker_init,
            initargs=(os.getpid(),),
        )


def check_started(pool: ProcessPoolExecutor, n_workers: int) -> None:
    """Raise `WorkerPoolError` where a worker of the broken `pool` exited with `UNGUARDED_EXIT`:
    the main module, imported again in it, starts the MPC's pool outside the main guard. Waits
    up to 2 s for the exit status of workers still running (the pool ends them once broken)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    codes: list[int | None] = []
    for _ in range(40):  # the pool's own thread reaps its dead workers: wait for their status
        codes = [getattr(p, "exitcode", None) for p in procs]
        if UNGUARDED_EXIT in codes or None not in codes:
            break
        time.sleep(0.05)
    if UNGUARDED_EXIT in codes:
        main = getattr(sys.modules.get("__main__"), "__file__", None) or "the main module"
        raise WorkerPoolError(guard_message(n_workers, str(main)))


@contextlib.contextmanager
def stop_signals_blocked():
    """Block the stop signals in this thread while the pool may start workers: a worker
    inherits the mask, so a Ctrl-C that comes before its initializer (`pool_worker_init`)
    cannot kill it; the training process gets the signal once it is unblocked."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def discard_pool(pool: ProcessPoolExecutor) -> None:
    """End a pool that lost a worker or hung: its workers are killed (a hung one would outlive
    `shutdown`), its queued rows cancelled; returns without waiting."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        with contextlib.suppress(Exception):
            proc.kill()
    pool.shutdown(wait=False, cancel_futures=True)
