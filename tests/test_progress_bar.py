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


def test_a_resumed_run_never_draws_zero_or_a_negative_rate():
    """Resumed at 30 of 75 on tqdm's own clock: every frame drawn shows at least 30/75, and no
    rate below zero."""
    import re

    out = io.StringIO()
    bar = ProgressBar(75, 30, "restaurant eps=0.2", file=out, mininterval=0)
    for it in (31, 32, 33):
        bar.row(_row(it))
    bar.close()
    frames = [f for f in out.getvalue().split("\r") if "/75" in f]
    counts = [int(m) for m in re.findall(r"(\d+)/75", "".join(frames))]
    assert counts and min(counts) >= 30, frames
    assert not re.search(r"-\d[\d.]*\s*(it/s|s/it)", out.getvalue()), frames


def test_not_a_terminal_gets_lines_not_a_bar(monkeypatch, capsys):
    """stderr a file or a pipe: one line at the first iteration and at each tenth, no bar."""
    import types

    from mpcpearl_jax.cli import progress

    cfg = types.SimpleNamespace(
        env="restaurant", train=types.SimpleNamespace(iterations=20, eps=0.2)
    )
    monkeypatch.setattr(progress, "_is_terminal", lambda stream: False)
    lines = progress.progress_bar(cfg, 5)
    assert isinstance(lines, progress.ProgressLines)
    for it in range(6, 21):
        lines.row(_row(it))
    lines.close()
    err = capsys.readouterr().err
    assert "\r" not in err and "|" not in err
    got = [int(x.split("iteration ")[1].split("/")[0]) for x in err.splitlines()]
    assert got == [6, 8, 10, 12, 14, 16, 18, 20], err
    assert "episode return=-123" not in err and "episode return -123" in err
