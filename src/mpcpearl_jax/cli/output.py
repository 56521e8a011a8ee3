"""A standard output that breaks under a command (a closed pipe: `| head -1`; a full disk:
`> /dev/full`) without losing its work: `guarded_stdout` keeps the command going (what it
prints afterwards is dropped), and the command ends with one line on stderr instead of a
BrokenPipeError or OSError traceback."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import Any


class GuardedStdout:
    """`stream` whose writes and flushes stop raising once it broke: the first OSError is kept
    in `broken`, the file descriptor is pointed at /dev/null (so the interpreter's last flush
    does not fail again), and what follows is dropped."""

    def __init__(self, stream: Any) -> None:
        self.stream = stream
        self.broken: OSError | None = None

    def _failed(self, e: OSError) -> None:
        self.broken = e
        with contextlib.suppress(OSError, ValueError, AttributeError):
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self.stream.fileno())
            os.close(null)

    def write(self, text: str) -> int:
        if self.broken is None:
            try:
                return self.stream.write(text)
            except OSError as e:
                self._failed(e)
        return len(text)

    def flush(self) -> None:
        if self.broken is None:
            try:
                self.stream.flush()
            except OSError as e:
                self._failed(e)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stream, name)


def broken_line(e: OSError, written: str) -> str:
    """The one line on stderr of a standard output that broke (`written`: what is on disk)."""
    return f"error: standard output: {e.strerror or type(e).__name__}; {written}"


@contextlib.contextmanager
def guarded_stdout() -> Iterator[GuardedStdout]:
    """sys.stdout as a `GuardedStdout` while the block runs (the same one if it already is);
    after it, the guard's `broken` says whether the output broke."""
    if isinstance(sys.stdout, GuardedStdout):
        yield sys.stdout
        return
    guard = GuardedStdout(sys.stdout)
    sys.stdout = guard  # type: ignore[assignment]
    try:
        yield guard
    finally:
        guard.flush()
        if sys.stdout is guard:
            sys.stdout = guard.stream
