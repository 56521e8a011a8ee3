"""A training command whose stdout closes under it (`| head`): one line on stderr that says what
is saved and that the same command with --resume finishes the run, exit code 2, no traceback
and no bare "[Errno 32] Broken pipe"."""

from __future__ import annotations

import io
import sys

import pytest

from mpcpearl_jax.cli import train as cli_train


class _ClosingPipe(io.StringIO):
    """stdout whose reader goes away once a line containing `at` is written."""

    def __init__(self, at: str):
        super().__init__()
        self.at, self.closed_pipe = at, False

    def write(self, text: str) -> int:
        if self.closed_pipe or self.at in text:
            self.closed_pipe = True
            raise BrokenPipeError(32, "Broken pipe")
        return super().write(text)


def _fake_train(stage: str):
    def train(cfg, out, minutes=None, *, label=None, options=None):
        info = {"stopped": "done", "iterations": cfg.train.iterations, "train_s": 1.0}
        if stage == "after":
            options.on_trained(info)  # prints "trained in ...; evaluating"
        results = {"metrics": {}}
        return None, results

    return train


@pytest.mark.parametrize(
    "stage, breaks_at, says",
    [
        ("after", "trained in", "--resume runs the final evaluation"),
        ("start", "[restaurant]", "nothing was trained"),
    ],
)
def test_a_closed_output_says_what_resume_does(
    stage, breaks_at, says, tmp_path, monkeypatch, capsys
):
    monkeypatch.setattr(cli_train, "train", _fake_train(stage))
    pipe = _ClosingPipe(breaks_at)
    monkeypatch.setattr(sys, "stdout", pipe)
    argv = ["--preset", "smoke", "--iterations", "2", "--out", str(tmp_path / "run")]
    code = cli_train.main("restaurant", argv)
    err = capsys.readouterr().err
    assert code == 2
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: the output closed (broken pipe)") and says in line, err
    assert "Traceback" not in err and "[Errno 32]" not in err


def test_a_closed_output_after_the_results_are_written(tmp_path, monkeypatch, capsys):
    """The results table is printed after results.json: the line says the run is finished."""
    monkeypatch.setattr(cli_train, "train", _fake_train("done"))
    monkeypatch.setattr(cli_train._Run, "report", lambda *a: (_ for _ in ()).throw(BrokenPipeError))
    monkeypatch.setattr(sys, "stdout", _ClosingPipe("never"))
    code = cli_train.main("restaurant", ["--preset", "smoke", "--out", str(tmp_path / "r")])
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert code == 2 and "the run is finished" in line and str(tmp_path / "r") in line
