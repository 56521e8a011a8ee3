"""The training commands' progress: a tqdm bar for the iterations of MPC-PEARL (an algorithm
with a line of its own, `Algorithm.progress_line`, prints that line per iteration instead)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

from mpcpearl_jax.distributed import is_primary


def progress_bar(cfg: Any, done: int) -> ProgressBar | ProgressLines | None:
    """The training command's progress for a run of `cfg` with `done` iterations finished
    (process 0 only): a bar on a terminal, plain lines (`ProgressLines`) when stderr is a file
    or a pipe."""
    if not is_primary():
        return None
    label = f"{cfg.env} eps={cfg.train.eps}"
    if not _is_terminal(sys.stderr):
        return ProgressLines(cfg.train.iterations, done, label)
    return ProgressBar(cfg.train.iterations, done, label)


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class ProgressLines:
    """The progress where stderr is not a terminal (a log file, a pipe): one line on stderr at
    the first iteration and at each tenth of the run, with `PROGRESS_FIELDS`; no bar redrawn
    into the file."""

    def __init__(self, total: int, done: int, label: str, file: Any = None):
        self.total, self.label, self.file = total, label, file
        self.next = done + 1  # the first iteration of this process is always reported

    def row(self, row: dict[str, Any]) -> None:
        it = int(row["iteration"])
        if it < self.next and it != self.total:
            return
        step = max(self.total // 10, 1)
        self.next = (it // step + 1) * step
        fields = ", ".join(f"{k} {v}" for k, v in progress_fields(row).items())
        line = f"{self.label}: iteration {it}/{self.total}" + (f" ({fields})" if fields else "")
        print(line, file=self.file or sys.stderr, flush=True)

    def close(self) -> None:
        pass


class ProgressBar:
    """The training command's progress bar (tqdm): "compiling (first iteration, about a
    minute)" until the first iteration of this process ends (it compiles the training
    programs); then the time that took, and a rate and ETA from the iterations after it only;
    `PROGRESS_FIELDS` as self-explaining fields. `clock` (seconds) and `tqdm_kw` are for tests."""

    def __init__(
        self,
        total: int,
        done: int,
        label: str,
        clock: Callable[[], float] = time.time,  # tqdm's own clock
        **tqdm_kw: Any,
    ):
        from tqdm import tqdm

        self.label, self.clock, self.t0, self.first = label, clock, clock(), True
        self.bar = tqdm(
            total=total, initial=done, desc=f"{label}: {COMPILING}", dynamic_ncols=True, **tqdm_kw
        )
        self.bar._time = clock  # tqdm's clock, the same as ours
        self._restart(done)

    def _restart(self, n: int) -> None:
        """`n` done; the clock and the smoothed rate start again from now (what tqdm's `reset`
        does, without drawing 0/N and a negative rate in between)."""
        from tqdm.std import EMA

        bar = self.bar
        bar.initial = bar.n = bar.last_print_n = n
        bar.last_print_t = bar.start_t = self.clock()
        bar._ema_dn, bar._ema_dt = EMA(bar.smoothing), EMA(bar.smoothing)
        bar._ema_miniters = EMA(bar.smoothing)
        bar.refresh()

    def row(self, row: dict[str, Any]) -> None:
        """A finished iteration's metrics row."""
        if self.first:  # the first iteration compiled: the rate (and ETA) start after it
            self.first = False
            took = self.bar.format_interval(self.clock() - self.t0)
            self.bar.set_description(f"{self.label} (first iteration, with compiling: {took})")
            self._restart(row["iteration"])
        else:
            self.bar.update(row["iteration"] - self.bar.n)
        self.bar.set_postfix(progress_fields(row))

    def close(self) -> None:
        self.bar.close()


# the progress bar before the first iteration, which compiles the training programs
COMPILING = "compiling (first iteration, about a minute)"

# the progress bar's fields (also in the training command's --help): label, row key, format
PROGRESS_FIELDS = (
    ("episode return", "train_return", "{:.0f}"),  # mean over the iteration's training episodes
    ("MPC-acted steps", "train_mpc_share", "{:.0%}"),  # share of their steps the MPC acted
    ("test SR", "test_SR", "{:.2f}"),  # success rate on the test tasks (at evaluations)
    ("test CFR", "test_CFR", "{:.2f}"),  # collision-free rate on the test tasks
)


def progress_fields(row: dict[str, Any]) -> dict[str, str]:
    """The progress bar's postfix of a metrics row: each `PROGRESS_FIELDS` field the row has."""
    return {label: fmt.format(row[key]) for label, key, fmt in PROGRESS_FIELDS if key in row}
