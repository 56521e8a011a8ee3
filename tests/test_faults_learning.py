"""Fault injection on runs with a time budget (`experiments.restaurant --minutes`): stopped by
Ctrl-C and resumed exactly; the long variant (the command line, Ctrl-C then kill -9 then
--resume) is marked slow."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from faults_helpers import (
    ROOT,
    _env,
    _interrupted_at,
    _sigint_when,
    assert_same_run,
    kill_when,
    learning_args,
    rows_at_least,
)

from mpcpearl_jax.runfolder import LOG_FILE, read_log


class _Tick:
    """A fake clock for the training command on a time budget: every call is one second later,
    so that each iteration takes one training second; once metrics.jsonl in `sigint_log` holds
    `sigint_rows` rows, the next call sends this process a SIGINT (a real Ctrl-C)."""

    def __init__(self, sigint_log: Path | None = None, sigint_rows: int = 0):
        self.t, self.log, self.rows, self.sent = 0.0, sigint_log, sigint_rows, False

    def __call__(self) -> float:
        if self.log is not None and not self.sent and rows_at_least(self.log, self.rows)():
            self.sent = True
            os.kill(os.getpid(), signal.SIGINT)
        self.t += 1.0
        return self.t


def _points(run: Path) -> list[dict]:
    skip = {"wall_minutes", "eval_s"}
    rec = json.loads((run / "curve.json").read_text())
    return [{k: v for k, v in p.items() if k not in skip} for p in rec["points"]]


@pytest.mark.slow  # the time-budget run's Ctrl-C resume (~50 s)
def test_learning_run_stops_on_ctrl_c_and_resumes_exactly(tmp_path, monkeypatch, capsys):
    """A time-budget run stopped by Ctrl-C in its fifth iteration (a fake clock: one second per
    iteration, 6 s of budget, an evaluation every 3 s) saves iteration 4 and exits 130 with one
    line; --resume ends identical to a run never stopped: checkpoint, policy, metrics and the
    curve points (the budget counts the 4 s already trained)."""
    from mpcpearl_jax.cli.train import main

    monkeypatch.setattr(
        "mpcpearl_jax.training.final.final_evaluation", lambda *a, **k: {}
    )  # not needed
    ref, run = tmp_path / "ref", tmp_path / "run"
    assert main("restaurant", learning_args(ref, 0.1, 0.05), clock=_Tick()) == 0
    capsys.readouterr()
    assert main("restaurant", learning_args(run, 0.1, 0.05), clock=_Tick(run, 4)) == 130
    err = [x for x in capsys.readouterr().err.splitlines() if not x.startswith("warning: 1-min")]
    assert [x for x in err if x.strip()][-1] == "interrupted at iteration 4; continue with --resume"
    assert "Traceback" not in "\n".join(err)
    assert (run / "checkpoints" / "4").is_dir() and len(read_log(run / LOG_FILE)) == 4
    rec = json.loads((run / "curve.json").read_text())
    assert rec["stopped"] == "interrupted" and [p["iteration"] for p in rec["points"]] == [0, 3]
    assert json.loads((run / "config.json").read_text())["train"]["iterations"] == 4
    assert main("restaurant", learning_args(run, 0.1, 0.05, "--resume"), clock=_Tick()) == 0
    assert_same_run(ref, run)
    assert _points(ref) == _points(run) and [p["iteration"] for p in _points(run)] == [0, 3, 6]
    assert json.loads((run / "curve.json").read_text())["resumed_at_iteration"] == 4


@pytest.mark.slow  # the Ctrl-C resume of the same harness is tested exactly above (~35 s)
def test_learning_run_ctrl_c_then_kill9_then_resume(tmp_path, monkeypatch):
    """The command line: Ctrl-C gives exit 130 and one line within seconds, with the checkpoint,
    config.json and curve saved; a --resume killed with SIGKILL loses at most the iteration under
    way (a checkpoint every iteration here); the next --resume continues the curve and the log
    where the last checkpoint left them."""
    from mpcpearl_jax.cli.train import main

    run, log = tmp_path / "run", tmp_path / "log.txt"
    cmd = [sys.executable, "-m", "experiments.restaurant", *learning_args(run, 10, 5)]
    with open(log, "a") as f:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=_env())
    t_sig = _sigint_when(proc, rows_at_least(run, 2))
    assert proc.wait(timeout=60) == 130
    assert time.monotonic() - t_sig < 15
    text = log.read_text()
    n = _interrupted_at(text)
    assert "Traceback" not in text
    assert n >= 2 and (run / "checkpoints" / str(n)).is_dir()
    assert json.loads((run / "curve.json").read_text())["stopped"] == "interrupted"
    assert json.loads((run / "config.json").read_text())["train"]["iterations"] == n
    with open(log, "a") as f:
        proc = subprocess.Popen(
            [*cmd, "--resume"], cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=_env()
        )
    assert kill_when(proc, rows_at_least(run, n + 2))
    before = read_log(run / "curve-points.jsonl")
    monkeypatch.setattr("mpcpearl_jax.training.final.final_evaluation", lambda *a, **k: {})
    # a budget already spent: no further iteration, the last point evaluated, the curve written
    assert main("restaurant", learning_args(run, 0.01, 0.005, "--resume")) == 0
    rows = read_log(run / LOG_FILE)
    done = rows[-1]["iteration"]
    assert [r["iteration"] for r in rows] == list(range(1, done + 1)) and done >= n + 1
    points = read_log(run / "curve-points.jsonl")
    kept = [p for p in before if p["iteration"] <= done]
    assert points[: len(kept)] == kept and points[-1]["iteration"] == done
    assert json.loads((run / "curve.json").read_text())["iterations"] == done
