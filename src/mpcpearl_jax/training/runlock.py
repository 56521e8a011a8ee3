"""One writer per run folder: an exclusive `fcntl.flock` on <run>/.lock.

Every command that writes a run folder (training on iterations or minutes, `--resume`, GrBAL) takes
the lock before it writes anything there and holds it until it ends. A second writer gets a
one-line `RunDirError` naming the holder's PID. The operating system drops the lock when its
process dies (SIGKILL, power loss), so a lock file left by a killed run never blocks a resume.
The lock is re-entrant within one process (a caller may take it before `run.open_session` takes
it again); with several processes of one distributed run, process 0 takes it.
"""

from __future__ import annotations

import errno
import fcntl
import os
import socket
from pathlib import Path

from mpcpearl_jax.errors import RunDirError
from mpcpearl_jax.notices import warn
from mpcpearl_jax.validate import not_writable

LOCK_FILE = ".lock"
_HELD: dict[str, list[int]] = {}  # real path of the folder -> [fd, holders in this process]


def _not_writable(path: Path, e: OSError) -> RunDirError:
    return RunDirError(not_writable(path, e))


def _holder(fd: int) -> str:
    """'PID n' (on host h when it is another host) from the lock file, as far as it can be read."""
    try:
        text = os.pread(fd, 200, 0).decode(errors="replace").split()
    except OSError:
        text = []
    if not text or not text[0].isdigit():
        return "another process"
    host = f" on host {text[1]}" if len(text) > 1 and text[1] != socket.gethostname() else ""
    return f"PID {text[0]}{host}"


class RunLock:
    """The lock of `run_dir` (created if needed), held until `release()` (or the end of a `with`
    block, or of the process). enabled=False gives a lock that holds nothing (processes other
    than process 0 of a distributed run). RunDirError naming the folder when the folder cannot
    be created or another process holds the lock."""

    def __init__(self, run_dir: str | Path, enabled: bool = True):
        self.run_dir = Path(run_dir)
        self._key: str | None = None
        if enabled:
            self._acquire()

    def _acquire(self) -> None:
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise _not_writable(self.run_dir, e) from e
        key = os.path.realpath(self.run_dir)
        if key in _HELD:
            _HELD[key][1] += 1
            self._key = key
            return
        path = self.run_dir / LOCK_FILE
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise _not_writable(self.run_dir, e) from e
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
                holder = _holder(fd)
                os.close(fd)
                raise RunDirError(
                    f"{self.run_dir}: {holder} is writing this run folder; wait for it to end "
                    "(or stop it), or choose another --out"
                ) from None
            # e.g. a network file system without locks: go on unprotected
            warn(f"warning: {path}: cannot lock ({e.strerror}); nothing stops a second writer")
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        except OSError as e:
            os.close(fd)
            raise RunDirError(
                f"{path}: cannot write ({e.strerror or type(e).__name__}); free some space or "
                "choose another --out"
            ) from e
        _HELD[key] = [fd, 1]
        self._key = key

    @property
    def held(self) -> bool:
        return self._key is not None

    def release(self) -> None:
        """Give the lock up (once; later calls do nothing). The file stays: removing it would
        let two processes lock two different files of the same name."""
        key, self._key = self._key, None
        if key is None or key not in _HELD:
            return
        _HELD[key][1] -= 1
        if _HELD[key][1] == 0:
            os.close(_HELD.pop(key)[0])

    def __enter__(self) -> RunLock:
        return self

    def __exit__(self, *exc) -> None:
        self.release()
