"""`mpcpearl_jax.train` on a time budget with the caller's clock and callbacks
(`TrainOptions.clock`, `TrainOptions.on_row`): a clock that runs backwards or stands still is a
ValueError naming the clock (it would never end the budget), and `on_row` sees every iteration's
row in the minutes mode as in the iterations mode. A fake trainer and run session stand in for
the real ones (no compilation): what is tested is `train`'s wiring and the loop's rules."""

from __future__ import annotations

import contextlib
import types

import numpy as np
import pytest

from mpcpearl_jax.api import train as entry
from mpcpearl_jax.config import preset
from mpcpearl_jax.runfolder import LOG_FILE, read_log
from mpcpearl_jax.training.final import TrainOptions
from mpcpearl_jax.training.loop import Progress, train_loop
from mpcpearl_jax.training.run import Session


class _Trainer:
    """Enough of a Trainer for the minutes mode: an iteration adds 1 to the state and reads the
    clock; evaluate returns fixed metrics."""

    def __init__(self, cfg):
        self.cfg = cfg
        self.num_train, self.horizon = 8, 80
        self.env = types.SimpleNamespace(config=None)
        self.train_tasks = None

    def iteration(self, state, stop=None):
        return state + 1, {"iteration": state + 1, "train_return": -1.0}

    def evaluate(self, state, tasks=None, online=False):
        return {"SR": 0.5, "CFR": 0.0, "TT": 80.0, "SPL": 0.0, "MGD": 1.0, "return": -1.0}


class _Session(Session):
    """The run session without orbax: a checkpoint is its iteration, recorded."""

    def save(self, iteration, state):
        self.saved_at.append(iteration)


class _Forward:
    """One second later at every call."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += 1.0
        return self.t


class _Broken:
    """A clock that runs backwards (step -1) or stands still (step 0); after `limit` calls it
    fails the test: a training that never ends its budget."""

    def __init__(self, step: float, limit: int = 500):
        self.t, self.step, self.calls, self.limit = 1000.0, step, 0, limit

    def __call__(self):
        self.calls += 1
        if self.calls > self.limit:
            raise AssertionError(f"the budget never ended ({self.calls} clock calls)")
        self.t += self.step
        return self.t


@pytest.fixture
def fake_run(monkeypatch, tmp_path):
    """`train`'s run session and final evaluation replaced by fakes: -> the config."""
    import mpcpearl_jax.envs as envs

    cfg = preset("smoke")

    @contextlib.contextmanager
    def open_session(cfg, out, resume, **kw):
        out.mkdir(parents=True, exist_ok=True)
        sess = _Session(cfg, out, _Trainer(cfg), 0)
        sess.saved_at = []
        yield sess

    val = types.SimpleNamespace(start=np.zeros((3, 3)))
    monkeypatch.setattr(entry, "open_session", open_session)
    monkeypatch.setattr(entry, "finish", lambda *a, **k: {})
    monkeypatch.setattr(entry, "load_at_start", lambda: None)  # no busy-machine warning
    monkeypatch.setattr(envs, "validation_tasks", lambda *a, **k: (val, "val"))
    return cfg


def test_on_row_sees_every_row_on_a_time_budget(fake_run, tmp_path):
    """TrainOptions.on_row: every iteration's row, with the evaluation's fields where it
    evaluated (as in the iterations mode), on a time budget too."""
    rows, points = [], []
    opts = TrainOptions(clock=_Forward(), on_row=rows.append, on_point=points.append)
    entry.train(fake_run, tmp_path / "run", 0.05, options=opts)
    logged = [r["iteration"] for r in read_log(tmp_path / "run" / LOG_FILE)]
    assert logged and [r["iteration"] for r in rows] == logged
    evaluated = [r["iteration"] for r in rows if "test_SR" in r]
    assert evaluated == [p["iteration"] for p in points[1:]]  # the minute-0 point has no row
    assert rows[-1]["iteration"] in evaluated and rows[-1]["val_SR"] == 0.5


@pytest.mark.parametrize("step, says", [(-1.0, "ran backwards"), (0.0, "stood still")])
def test_a_clock_that_does_not_move_forward_is_an_error_naming_it(fake_run, tmp_path, step, says):
    """A budget timed by a clock that runs backwards (or stands still) would never end: the
    training stops with a ValueError naming the clock."""
    opts = TrainOptions(clock=_Broken(step))
    with pytest.raises(ValueError, match=rf"clock {says}.*TrainOptions\.clock"):
        entry.train(fake_run, tmp_path / "run", 0.05, options=opts)


def test_the_loop_refuses_a_backwards_clock_after_one_iteration():
    clock = _Broken(-1.0)
    trainer = _Trainer(None)
    with pytest.raises(ValueError, match="clock ran backwards"):
        train_loop(
            trainer,
            0,
            Progress(),
            until=lambda p: p.train_s >= 3.0,
            on_row=lambda row, s, p: None,
            log=lambda row: None,
            save=None,
            clock=clock,
        )
    assert clock.calls <= 3
