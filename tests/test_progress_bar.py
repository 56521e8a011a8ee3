"""The training command's progress bar (`cli.progress.ProgressBar`) tells the truth: it says it is
compiling during the first iteration, its ETA comes from the iterations after the first (whose
compilation would otherwise inflate it many times over), and its fields say what they are."""

from __future__ import annotations

import io

from mpcpearl_jax.cli.progress import COMPILING, ProgressBar


class _Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _eta(bar: ProgressBar) -> float:
    d = bar.bar.format_dict
    rate = d["rate"] or (d["n"] - d["initial"]) / d["elapsed"]
    return (d["total"] - d["n"]) / rate


def _row(it: int, **extra) -> dict:
    return {"iteration": it, "train_return": -123.4, "train_mpc_share": 0.125, **extra}


def test_compiling_first_then_an_eta_from_the_later_iterations_and_named_fields():
    """75 iterations: the first takes 77 s (compilation), the others 5 s. Before the first ends
    the bar says it is compiling; after iterations 2 and 4 the ETA is 5 s per iteration left
    (a rate over the first too would say 28 min, then 16 min)."""
    clock, out = _Clock(), io.StringIO()
    bar = ProgressBar(75, 0, "restaurant eps=0.2", clock=clock, file=out, mininterval=0)
    assert COMPILING in out.getvalue() and "compiling (first iteration" in out.getvalue()
    clock.t += 77.0
    bar.row(_row(1))
    assert "first iteration, with compiling: 01:17" in bar.bar.desc
    for it in range(2, 5):
        clock.t += 5.0
        bar.row(_row(it, test_SR=0.5, test_CFR=0.75) if it == 4 else _row(it))
        assert abs(_eta(bar) - 5.0 * (75 - it)) < 1e-6, (it, _eta(bar))
    text = out.getvalue()
    assert "episode return=-123" in text and "MPC-acted steps=12%" in text
    assert "test SR=0.50" in text and "test CFR=0.75" in text
    assert "ret=" not in text and "mpc=" not in text
    bar.close()


def test_a_resumed_run_counts_from_its_iteration():
    clock = _Clock()
    bar = ProgressBar(75, 30, "restaurant eps=0.2", clock=clock, file=io.StringIO())
    assert bar.bar.n == 30
    clock.t += 60.0
    bar.row(_row(31))
    clock.t += 4.0
    bar.row(_row(32))
    assert bar.bar.n == 32 and abs(_eta(bar) - 4.0 * 43) < 1e-6
    bar.close()
