"""The one training loop: Algorithm 1's outer loop with logging, evaluation and checkpoints.

`train_loop(trainer, state, progress, ...)` calls `trainer.iteration` until `until(progress)`
holds, in the spirit of brax's `train(..., progress_fn)`: what differs between callers is passed
in as rules and callbacks, so every caller gets the same Ctrl-C, checkpoint and log behaviour.
Its one caller is the run session (`training.run.Session.train`), which adds the run folder's
log, TensorBoard, Ctrl-C and write errors; the session's users keep only their rules:

- `experiments.restaurant` / `experiments.sidewalk` (`run.train_iterations`): a number of
  iterations, evaluation every `eval_interval` iterations, checkpoints every
  `checkpoint_interval`.
- the learning-curve harness (`experiments.learning.train_for`): a budget of training seconds,
  evaluation off the clock every so many training seconds, a checkpoint after every evaluation.
- GrBAL (`grbal.run.train_iterations`): iterations and an optional wall-clock budget.

After every iteration the loop builds the log row (the iteration's own log, `train_s`: seconds
spent in `trainer.iteration` over the run's lifetime, `wall_s`: seconds since the run started,
and the evaluation's fields when `evaluate_after(progress)` says so or training ends), hands it
to `on_row` (which writes it), and saves a checkpoint through `save(iteration, state)` when
the checkpoint rule says so. `stop()` (Ctrl-C) is polled before every iteration and inside
it: between iterations the state is whole, so it is saved (if not yet) and the loop returns with
`progress.stopped == "interrupted"`; inside an iteration `trainer.iteration` raises
`IterationAbandoned` (its state was consumed), which propagates with `progress` telling the last
saved iteration. `TrainingDiverged` propagates the same way.
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
    "done" or "interrupted"; log: the last iteration's own log (`trainer.iteration`'s).
    """

    iterations: int = 0
    saved: int = -1
    train_s: float = 0.0
    wall_s0: float = 0.0
    first_iteration_s: float | None = None
    stopped: str | None = None
    log: dict[str, Any] | None = None


def train_loop(
    trainer,
    state,
    progress: Progress,
    *,
    until: Callable[[Progress], bool],
    save: Callable[[int, Any], None] | None,
    on_row: Callable[[dict[str, Any]], None],
    evaluate_after: Callable[[Progress], bool] = lambda p: False,
    evaluate: Callable[[Any, Progress], dict[str, Any]] | None = None,
    checkpoint_after: Callable[[Progress, bool], bool] = lambda p, evaluated: False,
    stop: Callable[[], bool] | None = None,
    clock: Callable[[], float] = time.perf_counter,
):
    """Train until `until(progress)`; -> the state (see module doc). save=None: no checkpoint.

    evaluate(state, progress) -> fields merged into the row (the caller times it; it is never
    counted in train_s). checkpoint_after(progress, evaluated): whether to save after this
    iteration (besides the end of training and a stop request, which always save).
    """
    stopping = stop or (lambda: False)
    kw = {"stop": stop} if stop is not None else {}
    t0 = clock()

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
        state, log = trainer.iteration(state, **kw)  # IterationAbandoned, TrainingDiverged
        dt = clock() - t
        progress.train_s += dt
        if progress.first_iteration_s is None:
            progress.first_iteration_s = dt
        progress.iterations, progress.log = log["iteration"], log
        row = dict(log, train_s=progress.train_s, wall_s=progress.wall_s0 + clock() - t0)
        evaluated = evaluate is not None and (until(progress) or evaluate_after(progress))
        if evaluated:
            row.update(evaluate(state, progress))
        on_row(row)
        if until(progress) or checkpoint_after(progress, evaluated) or stopping():
            checkpoint()
    progress.stopped = "done"
    return state
