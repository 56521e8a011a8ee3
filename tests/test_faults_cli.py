"""Fault injection on the command lines' input: wrong options and --set values, checkpoint
mismatches, a folder that is not a run, an unreachable coordinator, oversized size fields and the
evaluation's unwritable --out and reversed ranges are one-line errors that write nothing."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from faults_helpers import ROOT, _env, _make_unwritable, _one_line_error, small_args

from mpcpearl_jax.cli.args import build_config, parser
from mpcpearl_jax.cli.train import main
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.runfolder import LOG_FILE


@pytest.mark.parametrize(
    "sets, needle",
    [
        (["mpc.nosuch=1"], "MPCConfig has no field(s) ['nosuch']"),
        (["mpc.alpha=5"], "MPCConfig.alpha: must lie in (0, 1)"),
        (["env.nosuch=1"], "NavConfig has no field(s) ['nosuch']"),
        (["env.dt=-1"], "NavConfig.dt"),
        (["train.eps=true"], "TrainConfig.eps must be a number, not a boolean"),
        (["train.eps=True"], "TrainConfig.eps must be a number, not a boolean"),
        (["pearl.use_context=maybe"], "PearlConfig.use_context must be true or false"),
        (["train.iterations=false"], "TrainConfig.iterations must be an int, not a boolean"),
    ],
)
def test_config_errors_are_one_line_and_write_nothing(tmp_path, capsys, sets, needle):
    argv = ["--preset", "smoke", "--eps", "0", "--out", str(tmp_path / "r")]
    line = _one_line_error(capsys, argv + [a for s in sets for a in ("--set", s)])
    assert needle in line
    assert not (tmp_path / "r" / "config.json").exists()


def test_boolean_options_are_read_by_field_type():
    def cfg(*sets):
        argv = ["--preset", "smoke"] + [a for s in sets for a in ("--set", s)]
        return build_config(parser("restaurant").parse_args(argv), "restaurant")

    for text, value in [("False", False), ("false", False), ("0", False), ("True", True),
                        ("true", True), ("1", True)]:  # fmt: skip
        assert cfg(f"pearl.use_context={text}").pearl.use_context is value
        assert cfg(f"train.redraw_behaviours={text}").train.redraw_behaviours is value
    assert cfg("mpc.unsafe_recovery=False").mpc.unsafe_recovery is False
    assert cfg("train.eps=1").train.eps == 1 and cfg("mpc.r_safe=None").mpc.r_safe is None
    with pytest.raises(ConfigError, match="TrainConfig.eps"):
        cfg("train.eps=false")


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(ConfigError):
        main("restaurant", ["--preset", "smoke", "--set", "mpc.alpha=5", "--debug"])


def test_checkpoint_errors_are_one_line(tmp_path, capsys, ref0):
    line = _one_line_error(capsys, small_args(0.0, tmp_path / "nothing", 6, "--resume"))
    assert "no config.json" in line
    line = _one_line_error(capsys, [*small_args(0.0, ref0, 6, "--resume"), "--seed", "3"])
    assert "differs from the requested one in ['seed']" in line
    line = _one_line_error(capsys, small_args(0.0, ref0))
    assert "already holds checkpoints" in line


def test_compare_on_a_folder_that_is_not_a_run(tmp_path, capsys):
    from lab import compare

    (tmp_path / "empty").mkdir()
    assert compare.main([str(tmp_path / "empty"), "--out", str(tmp_path / "cmp")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {tmp_path / 'empty'}: not a run directory (no config.json)"]


def test_compare_gp_mpc_record_that_is_not_one_is_named(tmp_path, capsys):
    """`lab.compare RUN --gp-mpc NOTES.txt`: a JSONDecodeError naming no file (after the figure
    was drawn); a missing file was silently left out. Now one line naming the file, exit 2,
    before anything is written."""
    from lab import compare

    run = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2"
    notes = tmp_path / "NOTES.txt"
    notes.write_text("these are my notes\n")
    listing = tmp_path / "list.json"
    listing.write_text("[1, 2]")
    cases = [
        (notes, f"error: --gp-mpc {notes}: not valid JSON"),
        (tmp_path / "nope.json", f"error: --gp-mpc {tmp_path / 'nope.json'}: no such file"),
        (listing, f"error: --gp-mpc {listing}: not a record of experiments.gp_mpc"),
    ]
    out = tmp_path / "cmp"
    for path, expected in cases:
        assert compare.main([str(run), "--out", str(out), "--gp-mpc", str(path)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(expected) and "\n" not in err, err
    assert not out.exists()
    record = ROOT / "results" / "gp_mpc" / "restaurant_test.json"
    assert compare.main([str(run), "--out", str(out), "--gp-mpc", str(record)]) == 0
    assert "GP-MPC (this project, same test tasks): SR " in (out / "table.md").read_text()


def test_convergence_count_below_one_is_one_line(capsys):
    """`lab.convergence problems --count -1`: a numpy ValueError traceback."""
    from lab import convergence

    for count in ("0", "-1"):
        assert convergence.main(["problems", "--count", count]) == 2
        err = capsys.readouterr().err.strip()
        assert err == f"error: --count must be positive, got {count}"


@pytest.mark.slow  # (~13 s)
def test_unreachable_coordinator_is_a_one_line_error_in_bounded_time(tmp_path):
    """No coordinator at the address (process 1), or process 0 left alone: exit 2 and one line
    after --coordinator-timeout, not a C++ abort minutes later."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    cases = [("127.0.0.1:1", 1, "no answer within 3 s"), (f"127.0.0.1:{free}", 0, "not every")]
    for address, pid, needle in cases:
        t0 = time.monotonic()
        proc = subprocess.run(
            [sys.executable, "-m", "experiments.restaurant", "--preset", "smoke"]
            + ["--out", str(tmp_path / "r"), "--coordinator", address, "--num-processes", "2"]
            + ["--process-id", str(pid), "--coordinator-timeout", "3"],
            cwd=ROOT,
            env=_env(),
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 2, proc.stderr[-3000:]
        assert time.monotonic() - t0 < 60
        errors = [x for x in proc.stderr.splitlines() if x.startswith("error:")]
        assert len(errors) == 1 and errors[0].startswith(f"error: --coordinator {address}: ")
        assert needle in errors[0] and "Check failure" not in proc.stderr, proc.stderr
        assert not (tmp_path / "r").exists()


def test_size_fields_are_bounded_before_anything_is_written(tmp_path, capsys):
    from experiments import grbal
    from mpcpearl_jax.training.resources import check_fits

    out = tmp_path / "g"

    def grbal_error(horizon: int) -> list[str]:
        argv = ["--preset", "smoke", "--set", f"grbal.plan_horizon={horizon}", "--out", str(out)]
        assert grbal.main(argv) == 2
        return capsys.readouterr().err.strip().splitlines()

    assert grbal_error(100000000) == [
        "error: GrbalConfig.plan_horizon: must be at most 1000, got 100000000"
    ]
    assert not out.exists()
    err = grbal_error(500)  # within the bound, beyond the episode
    assert len(err) == 1 and "plan_horizon: must not exceed the episode length 80" in err[0]
    assert not (out / "config.json").exists() and not (out / LOG_FILE).exists()
    run = tmp_path / "r"
    line = _one_line_error(capsys, small_args(0.0, run, 2, "--set", "train.rl_capacity=1000000000"))
    assert line.startswith("error: train.rl_capacity") and "would need" in line
    assert not (run / "config.json").exists() and not (run / LOG_FILE).exists()
    assert not (run / "checkpoints").exists()
    with pytest.raises(ConfigError, match=r"f: x would need 1.0 GiB of memory, 512 MiB are free"):
        check_fits(2**30, "x", "f", free=2**29)


def test_evaluate_checks_its_output_folder_and_ranges_first(tmp_path, ref0, capsys):
    """An unwritable --out stops before the evaluation; reversed ranges are one-line errors."""
    from mpcpearl_jax.cli import evaluate

    locked = tmp_path / "locked"
    locked.mkdir()
    undo = _make_unwritable(locked)
    try:
        assert evaluate.main([str(ref0), "--animate", "--out", str(locked / "eval")]) == 2
    finally:
        undo()
    cap = capsys.readouterr()
    assert cap.err.strip().splitlines() == [
        f"error: --out {locked / 'eval'}: not writable ("
        + cap.err.split("not writable (", 1)[1].strip()
    ]
    assert "[evaluate]" not in cap.out and not (locked / "eval").exists()
    for argv, needle in (
        (["--task-seeds", "5-1"], "--task-seeds '5-1': the range 5-1 is reversed"),
        (["--tasks", "3-1"], "--tasks '3-1': the range 3-1 is reversed"),
        (["--tasks", "0,4-2"], "the range 4-2 is reversed"),
    ):
        assert evaluate.main([str(ref0), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
