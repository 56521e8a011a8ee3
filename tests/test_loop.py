"""mpcpearl_jax.training.loop.train_loop, the one training loop, with a fake trainer and a fake
clock: its rules (until, checkpoints), the one callback after every iteration (evaluating when
its rule says so and on the last iteration), rows, Ctrl-C between and inside iterations, and
errors propagating with the progress telling the last checkpoint."""

from __future__ import annotations

import pytest

from mpcpearl_jax.errors import TrainingDiverged
from mpcpearl_jax.training.loop import Progress, train_loop
from mpcpearl_jax.training.trainer import IterationAbandoned


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class FakeTrainer:
    """Each iteration takes `dt` fake seconds and adds 1 to the state; `fail` maps an iteration
    to the exception it raises."""

    def __init__(self, clock: Clock, dt: float = 2.0, fail=None, stop_inside=None):
        self.clock, self.dt, self.fail = clock, dt, fail or {}
        self.stop_inside = stop_inside

    def iteration(self, state, stop=None):
        it = state + 1
        if it in self.fail:
            raise self.fail[it]
        if stop is not None and self.stop_inside == it:  # stop() turned true inside it
            raise IterationAbandoned
        self.clock.t += self.dt
        return state + 1, {"iteration": it, "train_return": float(it)}


def _loop(trainer, state, progress, clock, **kw):
    rows, saves, evals = [], [], []

    def on_row(row, s, p):
        """Evaluates (0.5 fake seconds) every second iteration and on the last one."""
        if not (p.last or p.iterations % 2 == 0):
            return None
        evals.append(p.iterations)
        clock.t += 0.5
        return {"test_SR": s / 10, "eval_s": 0.5}

    defaults = dict(
        until=lambda p: p.iterations >= 5,
        save=lambda it, s: saves.append((it, s)),
        on_row=on_row,
        log=rows.append,
        checkpoint_after=lambda p, evaluated: p.iterations % 3 == 0,
        clock=clock,
    )
    defaults.update(kw)
    out = train_loop(trainer, state, progress, **defaults)
    return out, rows, saves, evals


def test_rules_rows_and_checkpoints():
    clock = Clock()
    p = Progress()
    state, rows, saves, evals = _loop(FakeTrainer(clock), 0, p, clock)
    assert state == 5 and p.stopped == "done" and p.iterations == 5 and p.saved == 5
    assert evals == [2, 4, 5]  # every second iteration, and at the end
    assert [it for it, _ in saves] == [3, 5]  # every third, and at the end
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4, 5]
    assert [r["train_s"] for r in rows] == [2.0, 4.0, 6.0, 8.0, 10.0]
    assert rows[1]["test_SR"] == 0.2 and "test_SR" not in rows[0]
    # wall_s is taken before the evaluation; train_s never counts it
    assert [r["wall_s"] for r in rows] == [2.0, 4.0, 6.5, 8.5, 11.0]
    assert p.first_iteration_s == 2.0 and p.log == {"iteration": 5, "train_return": 5.0}


def test_a_resumed_loop_continues_its_clocks_and_ends_at_once_when_done():
    clock = Clock()
    p = Progress(iterations=3, saved=3, train_s=6.0, wall_s0=100.0, first_iteration_s=9.0)
    state, rows, saves, _ = _loop(FakeTrainer(clock), 3, p, clock)
    assert [r["iteration"] for r in rows] == [4, 5] and rows[0]["train_s"] == 8.0
    assert rows[0]["wall_s"] == 102.0 and p.first_iteration_s == 9.0
    assert [it for it, _ in saves] == [5]
    done = Progress(iterations=5, saved=5)
    state, rows, saves, evals = _loop(FakeTrainer(clock), 5, done, clock)
    assert (state, rows, saves, evals, done.stopped) == (5, [], [], [], "done")


def test_ctrl_c_between_iterations_saves_the_whole_state():
    clock = Clock()
    flag = {"stop": False}

    def on_row(row, state, p):
        if row["iteration"] == 2:
            flag["stop"] = True  # pressed during iteration 2's bookkeeping

    p = Progress()
    rows = []
    state, _, saves, _ = _loop(
        FakeTrainer(clock),
        0,
        p,
        clock,
        stop=lambda: flag["stop"],
        on_row=on_row,
        log=rows.append,
    )
    assert p.stopped == "interrupted" and state == 2 and p.saved == 2
    assert [it for it, _ in saves] == [2] and [r["iteration"] for r in rows] == [1, 2]


def test_ctrl_c_inside_an_iteration_and_divergence_propagate_with_the_last_checkpoint():
    clock = Clock()
    p = Progress()
    with pytest.raises(IterationAbandoned):
        _loop(FakeTrainer(clock, stop_inside=4), 0, p, clock, stop=lambda: False)
    assert p.iterations == 3 and p.saved == 3 and p.stopped is None
    p = Progress()
    with pytest.raises(TrainingDiverged):
        _loop(FakeTrainer(clock, fail={5: TrainingDiverged("nan")}), 0, p, clock)
    assert p.iterations == 4 and p.saved == 3


def test_without_save_nothing_is_checkpointed_and_a_time_budget_stops_it():
    clock = Clock()
    p = Progress()
    state, rows, _, evals = _loop(
        FakeTrainer(clock, dt=3.0), 0, p, clock, save=None, until=lambda p: p.train_s >= 7.0
    )
    assert state == 3 and p.saved == -1 and evals == [2, 3]
    assert rows[-1]["train_s"] == 9.0
