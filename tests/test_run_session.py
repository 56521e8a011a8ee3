"""The run session (`training.run.open_session`) on folders that earlier processes left behind."""

from __future__ import annotations

import dataclasses
import json

import pytest

from mpcpearl_jax.config import preset
from mpcpearl_jax.errors import CheckpointError
from mpcpearl_jax.runfolder import LOG_FILE
from mpcpearl_jax.training.run import open_session


def _cfg():
    cfg = preset("smoke")
    return cfg.replace(train=dataclasses.replace(cfg.train, eps=0.0, iterations=2))


def _killed_during_first_save(run, config=True):
    """What SIGKILL during the first checkpoint's save leaves: orbax's temporary folder (and
    the run's config.json)."""
    tmp = run / "checkpoints" / "2.orbax-checkpoint-tmp-1764201234567"
    (tmp / "state").mkdir(parents=True)
    (tmp / "state" / "partial").write_bytes(b"\0" * 64)
    if config:
        (run / "config.json").write_text(_cfg().to_json())
    return tmp


def test_an_unfinished_checkpoint_is_no_checkpoint(tmp_path, capsys):
    """A save killed midway used to leave a folder that made a fresh start say 'already holds
    checkpoints' and --resume say 'nothing to resume': stuck until deleted by hand. It counts as
    no checkpoint and is removed when the run is opened, with one line saying so."""
    run = tmp_path / "run"
    tmp = _killed_during_first_save(run, config=False)
    with open_session(_cfg(), run) as sess:
        assert sess.done == 0 and sess.saved == -1
    assert not tmp.exists()
    assert "removed an unfinished checkpoint" in capsys.readouterr().err

    run2 = tmp_path / "run2"
    tmp2 = _killed_during_first_save(run2)
    with open_session(_cfg(), run2, resume=True) as sess:  # nothing logged: start at 0
        assert sess.done == 0
    assert not tmp2.exists()
    err = capsys.readouterr().err
    assert "removed an unfinished checkpoint" in err and "starting at iteration 0" in err


def test_resume_without_a_checkpoint_keeps_the_logged_iterations(tmp_path):
    run = tmp_path / "run"
    _killed_during_first_save(run)
    rows = [{"iteration": i, "train_s": float(i)} for i in (1, 2)]
    (run / LOG_FILE).write_text("".join(json.dumps(r) + "\n" for r in rows))
    with pytest.raises(CheckpointError, match="logs 2 iteration"):
        open_session(_cfg(), run, resume=True)
    assert len((run / LOG_FILE).read_text().splitlines()) == 2  # nothing erased


def test_a_failed_write_before_any_checkpoint_says_what_to_do():
    """A full disk before the first checkpoint used to end with 'no checkpoint is saved yet once
    the cause is fixed'."""
    import errno

    from mpcpearl_jax.training.run import write_error

    e = OSError(errno.ENOSPC, "No space left on device", "run/metrics.jsonl")
    assert str(write_error(e, -1)) == (
        "run/metrics.jsonl: cannot write (No space left on device); no checkpoint was saved yet:"
        " once the cause is fixed, start again with --overwrite"
    )
    assert str(write_error(e, 4)).endswith(
        "--resume continues from iteration 4 once the cause is fixed"
    )


def test_a_bad_line_inside_the_log_says_how_to_go_on(tmp_path):
    from mpcpearl_jax.runfolder import read_log

    path = tmp_path / LOG_FILE
    path.write_text('{"iteration": 1}\n{"iteration": 2, "x\n{"iteration": 3}\n')
    with pytest.raises(CheckpointError, match=r"line 2 is not JSON .*repair or delete that line"):
        read_log(path)
