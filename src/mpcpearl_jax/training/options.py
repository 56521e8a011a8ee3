"""What a caller of `mpcpearl_jax.train` chooses beside the config, the folder and the budget:
`TrainOptions` (resume or overwrite, a time budget's options, the callbacks through which a
caller sees the run; nothing in the library prints)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from typing import Any


@dataclasses.dataclass(frozen=True)
class TrainOptions:
    """What a caller of `train` chooses beside the config, the folder and the budget.

    resume: continue the run in `out` (its config, checkpoints and log); overwrite: replace the
    run in `out` (not both). A time budget's options: `eval_minutes` (minutes of training
    between the curve's evaluations, default minutes / 8), `policy_only` (policy.msgpack alone,
    no checkpoint to resume from), `record` (fields curve.json records, e.g. the command line's
    preset and argv) and `clock` (what times the budget; tests give a fake one). `tensorboard`:
    every metrics row also to <out>/tensorboard.

    The callbacks, each optional, are how a caller sees a run as it goes (nothing here prints):
    `on_start(session)` once the run folder is open, before the first iteration;
    `on_row(row)` after every iteration (its metrics row, with the evaluation's fields when it
    evaluated); `on_point(point)` at each eval point of a time budget; `on_trained(info)` once
    training stops, however it stops, before the final evaluation (info: the mode's record:
    "stopped", "iterations", "train_s", ...; a time budget's eval "points" too)."""

    resume: bool = False
    overwrite: bool = False
    eval_minutes: float | None = None
    policy_only: bool = False
    tensorboard: bool = False
    record: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    clock: Callable[[], float] = time.perf_counter
    on_start: Callable[[Any], None] | None = None
    on_row: Callable[[dict[str, Any]], None] | None = None
    on_point: Callable[[dict[str, Any]], None] | None = None
    on_trained: Callable[[dict[str, Any]], None] | None = None

    def __post_init__(self) -> None:
        """Each option's type checked at construction: TypeError naming the option."""

        def wrong(name: str, expected: str) -> TypeError:
            x = getattr(self, name)
            return TypeError(
                f"TrainOptions: {name} must be {expected}, not {type(x).__name__} {x!r}"
            )

        for name in ("resume", "overwrite", "policy_only", "tensorboard"):
            if not isinstance(getattr(self, name), bool):
                raise wrong(name, "True or False")
        m = self.eval_minutes
        if m is not None and (isinstance(m, bool) or not isinstance(m, (int, float))):
            raise wrong("eval_minutes", "a number of minutes (or None: minutes / 8)")
        if not isinstance(self.record, Mapping):
            raise wrong("record", "a mapping of the fields curve.json records")
        if not callable(self.clock):
            raise wrong("clock", "a function returning seconds")
        for name in ("on_start", "on_row", "on_point", "on_trained"):
            if getattr(self, name) is not None and not callable(getattr(self, name)):
                raise wrong(name, "a function (or None)")
