"""The commands' one error ladder: every error a command meets as one line on stderr and its
exit code (`one_line_errors`), the traceback only with --debug."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator

from mpcpearl_jax.cli.stopping import stop_exit_code


def error_line(e: BaseException) -> str:
    """One line for a command-line error: OSErrors name their file, others carry their own."""
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or type(e).__name__}"
    if isinstance(e, UnicodeDecodeError):
        return f"not a text file ({e.reason} at byte {e.start})"
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


class Outcome:
    """What `one_line_errors` leaves: the exit code of the error it reported (None: none)."""

    code: int | None = None


@contextlib.contextmanager
def one_line_errors(
    debug: bool = False, interrupted: str | None = "interrupted; continue with --resume"
) -> Iterator[Outcome]:
    """The commands' one error ladder, around their work: each error as one line on stderr
    (`error_line`; the traceback with `debug`) and its exit code in the yielded `Outcome`: 2 a
    config, data, checkpoint or run-folder error, an OS error (a file, permissions, a full disk)
    or XLA's out-of-memory error; 1 training diverged; `stop_exit_code()` a stop signal during
    training (`RunInterrupted`: its line), or a second one (KeyboardInterrupt: `interrupted`;
    None lets it through to the caller)."""
    from mpcpearl_jax.errors import CheckpointError, RunDirError, TrainingDiverged
    from mpcpearl_jax.training.run import RunInterrupted

    outcome = Outcome()
    try:
        yield outcome
    except RunInterrupted as e:  # the last finished iteration saved
        print(str(e), file=sys.stderr, flush=True)
        outcome.code = stop_exit_code()
    except KeyboardInterrupt:  # a second Ctrl-C: stopped at once, the last checkpoint stands
        if interrupted is None:
            raise
        print(interrupted, file=sys.stderr, flush=True)
        outcome.code = stop_exit_code()
    except TrainingDiverged as e:
        outcome.code = fail_line(e, 1, debug)
    except (ValueError, TypeError, OSError, CheckpointError, RunDirError) as e:
        outcome.code = fail_line(e, 2, debug)
    except RuntimeError as e:
        if not out_of_memory(e):
            raise
        outcome.code = fail_line(MemoryError(out_of_memory(e)), 2, debug)


def fail_line(e: BaseException, code: int = 2, debug: bool = False) -> int:
    """Print `e` as one line on stderr (`error_line`) and return `code`; with `debug`, raise it
    (its traceback)."""
    if debug:
        raise e
    print(f"error: {error_line(e)}", file=sys.stderr, flush=True)
    return code


def out_of_memory(e: BaseException) -> str:
    """The one line of XLA's out-of-memory error ('' for any other error)."""
    text = str(e)
    if "RESOURCE_EXHAUSTED" not in text or "memory" not in text.lower():
        return ""
    first = text.strip().splitlines()[0]
    return f"out of memory ({first}); lower the config's size fields (--set)"
