"""No command overwrites a result it did not make: a training of any family, an evaluation and an
export refuse a folder holding a run's records unless told to replace them, with one line, and
the folder stays byte-identical."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FINISHED = ROOT / "results" / "restaurant" / "main-default"  # a finished run, no checkpoints


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


@pytest.fixture
def finished(tmp_path):
    run = tmp_path / "run"
    shutil.copytree(FINISHED, run)
    return run


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_training_refuses_a_finished_run_without_overwrite(finished, capsys):
    """`experiments.restaurant --preset smoke --out <a finished run without checkpoints>` used
    to exit 0 with policy.msgpack, results.json and config.json replaced and metrics.jsonl cut
    from 75 lines to 4."""
    from mpcpearl_jax.cli.train import main

    before = _snapshot(finished)
    assert main("restaurant", ["--preset", "smoke", "--out", str(finished), "--no-progress"]) == 2
    line = _one_line(capsys)
    assert "holds a run's records" in line and "--overwrite" in line
    assert _snapshot(finished) == before


def test_grbal_refuses_a_finished_run_without_overwrite(finished, capsys):
    from experiments.grbal import main

    before = _snapshot(finished)
    assert main(["--preset", "smoke", "--out", str(finished), "--no-progress"]) == 2
    assert "holds a run's records" in _one_line(capsys)
    assert _snapshot(finished) == before


def test_overwrite_replaces_only_what_a_run_writes(finished):
    from mpcpearl_jax.config import preset
    from mpcpearl_jax.runfolder import RUN_RECORDS
    from mpcpearl_jax.training.run import open_session

    (finished / "notes.txt").write_text("mine")
    cfg = preset("smoke")
    cfg = cfg.replace(train=dataclasses.replace(cfg.train, eps=0.0))
    with open_session(cfg, finished, overwrite=True) as sess:
        assert sess.done == 0
    left = sorted(p.name for p in finished.iterdir())
    assert "notes.txt" in left and "eval" in left  # not a run's output: kept
    assert not list(finished.glob("trajectory_test*.png"))
    assert "results.json" not in left and "episode_test0.gif" not in left
    assert set(left) & set(RUN_RECORDS) == {"config.json", "metrics.jsonl", "network.json"}
    assert (finished / "metrics.jsonl").read_text() == ""  # the new run's, empty


def test_evaluate_never_writes_into_a_run_folder(finished, capsys):
    """`experiments.evaluate RUN --split val --tasks 0-1 --out RUN` used to replace the run's
    own results.json by a 2-task record."""
    from mpcpearl_jax.cli.evaluate import main

    before = _snapshot(finished)
    argv = [str(finished), "--split", "val", "--tasks", "0-1", "--figures", "none"]
    assert main([*argv, "--out", str(finished)]) == 2
    line = _one_line(capsys)
    assert "a run's folder" in line and "never writes over a run's records" in line
    assert _snapshot(finished) == before
    # an earlier evaluation's record is replaced only with --overwrite
    out = finished / "eval" / "again"
    out.mkdir(parents=True)
    (out / "results.json").write_text("{}")
    assert main([*argv, "--out", str(out)]) == 2
    assert "--overwrite" in _one_line(capsys)
    assert (out / "results.json").read_text() == "{}"
