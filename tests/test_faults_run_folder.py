"""Fault injection on the run folder: an unwritable checkpoints folder or a run folder that
cannot be created is named before training, and a second writer on a run folder (a new run, a
--resume, the learning harness, GrBAL) stops with one line naming the holder."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from faults_helpers import _env, _make_unwritable, _one_line_error, learning_args, small_args, spawn

from mpcpearl_jax.runfolder import LOG_FILE
from mpcpearl_jax.training.run import RunDirError, check_writable


def test_unwritable_checkpoints_folder_is_reported_before_training(tmp_path):
    run, log = tmp_path / "run", tmp_path / "log.txt"
    (run / "checkpoints").mkdir(parents=True)
    undo = _make_unwritable(run / "checkpoints")
    try:
        t0 = time.monotonic()
        proc = spawn(small_args(0.0, run), log, cli=True)
        assert proc.wait(timeout=60) == 2
        assert time.monotonic() - t0 < 30
    finally:
        undo()
    text = log.read_text()
    errors = [line for line in text.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, text
    assert errors[0].startswith(f"error: {run / 'checkpoints'}: not writable (")
    assert errors[0].endswith("); fix its permissions or choose another --out")
    assert "Traceback" not in text and not (run / "config.json").exists()


def test_run_folder_that_cannot_be_created_is_named(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(RunDirError, match=r"file/run: not writable"):
        check_writable(tmp_path / "file" / "run")


def _hold_lock(folder: Path) -> subprocess.Popen:
    code = (
        "import sys, time\nfrom mpcpearl_jax.training.runlock import RunLock\n"
        "RunLock(sys.argv[1])\nprint('locked', flush=True)\ntime.sleep(600)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True, env=_env()
    )
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_one_writer_per_run_folder(tmp_path, ref0, capsys):
    """While another process holds a run folder, a new run, a --resume, a time-budget run and
    GrBAL each stop with one line naming the holder's PID and write nothing; once the holder is
    killed (SIGKILL), its lock file no longer blocks anyone."""
    from experiments import grbal
    from mpcpearl_jax.cli.train import main
    from mpcpearl_jax.training.runlock import LOCK_FILE, RunLock

    new, old = tmp_path / "new", tmp_path / "old"
    shutil.copytree(ref0, old)
    before = (old / LOG_FILE).read_bytes()
    holders = [_hold_lock(new), _hold_lock(old)]
    try:
        busy = (
            "is writing this run folder; wait for it to end (or stop it), or choose another --out"
        )
        pid_new, pid_old = (f"PID {p.pid} {busy}" for p in holders)
        line = _one_line_error(capsys, small_args(0.0, new))
        assert line == f"error: {new}: {pid_new}"
        line = _one_line_error(capsys, small_args(0.0, old, 8, "--resume"))
        assert line == f"error: {old}: {pid_old}"
        assert main("restaurant", learning_args(new, 1, 0.5)) == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"error: {new}: {pid_new}"
        assert grbal.main(["--preset", "smoke", "--out", str(new)]) == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"error: {new}: {pid_new}"
        assert sorted(p.name for p in new.iterdir()) == [LOCK_FILE]
        assert (old / LOG_FILE).read_bytes() == before
    finally:
        for p in holders:
            p.kill()
            p.wait()
    with RunLock(new), RunLock(old):  # the stale lock files of killed holders
        assert (new / LOCK_FILE).read_text().split()[0] == str(os.getpid())
