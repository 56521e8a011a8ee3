"""The one training loop: Algorithm 1's outer loop with logging, evaluation and checkpoints.

`train_loop(trainer, state, progress, ...)` calls `trainer.iteration` until `until(progress)`
holds, in the spirit of brax's `train(..., progress_fn)`: after every iteration it hands the row
to the caller's one callback, `on_row(row, state, progress)`, which evaluates when its rule says
so (always on the last iteration, `progress.last`) and returns the evaluation's fields (None:
not evaluated) and prints; the loop merges them into the row, writes the row (`log`) and saves a
checkpoint through `save(iteration, state)` when the checkpoint rule says so. Its one caller is
the run session (`training.run.Session.train`), whose `log` writes the run folder's
metrics.jsonl and TensorBoard; the session's users keep only their rules and their callback:

- `experiments.restaurant` / `experiments.sidewalk` (`run.train_iterations`): a number of
  iterations, evaluation every `eval_interval` iterations, checkpoints every
  `checkpoint_interval`.
- training on a time budget (`budget.train_for`, `--minutes`): a budget of training seconds,
  evaluation off the clock every so many training seconds, a checkpoint after every evaluation.
- GrBAL (`grbal.run.train_iterations`): iterations and an optional wall-clock budget.

The row holds the iteration's own log, `train_s` (seconds spent in `trainer.iteration` over the
run's lifetime), `wall_s` (seconds since the run started, before the evaluation) and the
evaluation's fields. `stop()` (Ctrl-C, SIGTERM, SIGHUP) is polled before every iteration: the
state is whole there, so it is saved (if not yet) and the loop returns with
`progress.stopped == "interrupted"`. Inside an iteration it is polled only where stopping loses
no finished iteration (the last one is saved, or none has finished): `trainer.iteration` then
raises `IterationAbandoned` (its state was consumed), which propagates with `progress` telling
the last saved iteration; otherwise the iteration under way is finished, saved, and the loop
stops, so a run stopped before its first scheduled checkpoint still resumes from where it
stopped. `TrainingDiverged` propagates the same way.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any


@dataclasses.dataclass
class Progress:
    """Where a training loop stands; `train_loop` updates it in place.

    iterations: finished iterations (of the run, earlier processes included); saved: the
    iteration of the newest checkpoint (-1: none); train_s: seconds inside `trainer.iteration`
    over the run's lifetime; wall_s0: the run's wall seconds before this process; first_iteration_s:
    the first iteration's seconds (compilation included); stopped: None while running, then
    "done" or "interrupted"; log: the last iteration's own log (`trainer.iteration`'s); last:
    whether that iteration ends the training (`until` holds).
    """

    iterations: int = 0
    saved: int = -1
    train_s: float = 0.0
    wall_s0: float = 0.0
    first_iteration_s: float | None = None
    stopped: str | None = None
    log: dict[str, Any] | None = None
    last: bool = False


def train_loop(
    trainer,
    state,
    progress: Progress,
    *,
    until: Callable[[Progress], bool],
    on_row: Callable[[dict[str, Any], Any, Progress], dict[str, Any] | None],
    log: Callable[[dict[str, Any]], None],
    save: Callable[[int, Any], None] | None,
    checkpoint_after: Callable[[Progress, bool], bool] = lambda p, evaluated: False,
    stop: Callable[[], bool] | None = None,
    clock: Callable[[], float] = time.perf_counter,
):
    """Train until `until(progress)`; -> the state (see module doc). save=None: no checkpoint.

    on_row(row, state, progress) -> the evaluation's fields merged into the row, or None (the
    caller times its evaluation; it is never counted in train_s). log(row) writes the row.
    checkpoint_after(progress, evaluated): whether to save after this iteration (besides the end
    of training and a stop request, which always save).
    """
    stopping = stop or (lambda: False)

    def abandon() -> bool:  # inside an iteration only when that loses no finished iteration
        return stopping() and (save is None or progress.iterations == max(progress.saved, 0))

    kw = {"stop": abandon} if stop is not None else {}
    t0 = clock()
    still = 0  # iterations in a row over which the clock stood still

    def checkpoint() -> None:
        if save is not None and progress.saved != progress.iterations:
            save(progress.iterations, state)
            progress.saved = progress.iterations

    while not until(progress):
        if stopping():  # Ctrl-C between iterations: the state is whole, keep it
            checkpoint()
            progress.stopped = "interrupted"
            return state
        t = clock()
        state, it_log = trainer.iteration(state, **kw)  # IterationAbandoned, TrainingDiverged
        dt = clock() - t
        still = _check_clock(dt, still)
        progress.train_s += dt
        if progress.first_iteration_s is None:
            progress.first_iteration_s = dt
        progress.iterations, progress.log = it_log["iteration"], it_log
        progress.last = until(progress)
        row = dict(it_log, train_s=progress.train_s, wall_s=progress.wall_s0 + clock() - t0)
        fields = on_row(row, state, progress)
        if fields is not None:
            row.update(fields)
        log(row)
        if progress.last or checkpoint_after(progress, fields is not None) or stopping():
            checkpoint()
    progress.stopped = "done"
    return state


# a clock that stands still over this many iterations in a row never ends a time budget
STILL_ITERATIONS = 3


def _check_clock(dt: float, still: int) -> int:
    """An iteration's `dt` seconds by the loop's clock: a clock that runs backwards (dt < 0), or
    stands still over `STILL_ITERATIONS` iterations in a row, would never end a time budget:
    ValueError naming `clock`. -> the iterations in a row the clock stood still."""
    if dt < 0:
        raise ValueError(
            f"clock ran backwards ({dt:.6g} s over an iteration): the training's clock (clock, "
            "e.g. TrainOptions.clock) must return seconds that never decrease, as "
            "time.perf_counter does"
        )
    still = still + 1 if dt == 0 else 0
    if still >= STILL_ITERATIONS:
        raise ValueError(
            f"clock stood still over {still} iterations: the training's clock (clock, e.g. "
            "TrainOptions.clock) must return seconds that move forward, as time.perf_counter "
            "does"
        )
    return still
