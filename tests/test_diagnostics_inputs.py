"""The lab diagnostics' bad inputs are one line naming the flag, the folder or the file (exit
code 2), found before any long work: a run folder that is not there or does not load (every
diagnostic that takes --run or --runs), none given, a delay out of range, the clone's sizes,
the forecast without the egocentric observation, a label scale that cannot fit in memory, and
`lab.diagnostics.dagger --report` on a missing folder or on partial records."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2"
PAPER_RUN = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2-paper"  # no relative positions


def _fails(capsys, main, argv: list[str], *names: str) -> str:
    """`main(argv)` ends with exit code 2 and one stderr line naming each of `names`."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2, exc.value.code
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    line = err.splitlines()[-1]
    assert line.startswith("error: ") or "error:" in line, err
    for name in names:
        assert name in line, (name, err)
    return line


@pytest.fixture
def threads_kept():
    """The environment variables a diagnostic's --threads sets, restored."""
    import os

    saved = dict(os.environ)
    yield
    os.environ.clear()
    os.environ.update(saved)


@pytest.mark.parametrize(
    "module, flag",
    [
        ("crowd_cause", "--runs"),
        ("shield", "--runs"),
        ("dagger", "--run"),
        ("imitation", "--run"),
    ],
)
def test_a_run_folder_that_is_not_there_or_not_a_run_is_one_line(
    module, flag, tmp_path, capsys, threads_kept
):
    import importlib

    main = importlib.import_module(f"lab.diagnostics.{module}").main
    missing = tmp_path / "nonexistent"
    _fails(capsys, main, ["--tiny", flag, str(missing), "--out", str(tmp_path)], flag, "no such")
    empty = tmp_path / "empty"
    empty.mkdir()
    _fails(capsys, main, ["--tiny", flag, str(empty), "--out", str(tmp_path)], flag, "config.json")


@pytest.mark.parametrize("module", ["crowd_cause", "shield"])
def test_runs_with_no_folder_says_none_was_given(module, tmp_path, capsys, threads_kept):
    import importlib

    main = importlib.import_module(f"lab.diagnostics.{module}").main
    line = _fails(capsys, main, ["--tiny", "--runs", "--out", str(tmp_path)], "--runs")
    assert "no run folder given" in line and "restaurant" not in line


def test_shield_env_from_a_missing_folder(tmp_path, capsys, threads_kept):
    from lab.diagnostics import shield

    argv = ["--tiny", "--runs", str(RUN), "--env-from", str(tmp_path / "x"), "--out", str(tmp_path)]
    _fails(capsys, shield.main, argv, "--env-from", "config.json")


def test_crowd_cause_delay_out_of_range_before_any_work(tmp_path, capsys, threads_kept):
    from lab.diagnostics import crowd_cause

    for delay in ("100000", "0"):
        argv = ["--tiny", "--runs", str(RUN), "--delay", delay, "--out", str(tmp_path)]
        _fails(capsys, crowd_cause.main, argv, "--delay", delay)


@pytest.mark.parametrize("hidden", ["0", "128,0", "-4"])
def test_dagger_hidden_sizes_must_be_positive(hidden, tmp_path, capsys, threads_kept):
    from lab.diagnostics import dagger

    with pytest.raises(SystemExit) as exc:
        dagger.main(["--tiny", "--hidden", hidden, "--out", str(tmp_path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--hidden" in err.splitlines()[-1] and "Traceback" not in err


def test_imitation_select_seed_below_zero(tmp_path, capsys, threads_kept):
    from lab.diagnostics import imitation

    with pytest.raises(SystemExit) as exc:
        imitation.main(["--tiny", "--select-seed", "-1", "--out", str(tmp_path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--select-seed" in err.splitlines()[-1] and "Traceback" not in err


def test_dagger_forecast_asks_for_relative(tmp_path, capsys, threads_kept):
    """A run that does not observe relative positions: --forecast alone names the command's
    own fix, --relative (not a config field)."""
    from lab.diagnostics import dagger

    with pytest.raises(SystemExit) as exc:
        dagger.main(["--tiny", "--forecast", "2", "--run", str(PAPER_RUN), "--out", str(tmp_path)])
    assert exc.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--forecast" in line and "--relative" in line and "env.observe" not in line


def test_dagger_labels_that_cannot_fit_in_memory(tmp_path, capsys, monkeypatch, threads_kept):
    """--labels 100000 is refused before the first round (one line naming --labels), not
    gigabytes later; --labels 1 of the same size fits the same memory."""
    from lab.diagnostics import dagger
    from mpcpearl_jax.training import resources

    monkeypatch.setattr(resources, "free_bytes", lambda: 2**30)
    argv = ["--tiny", "--labels", "100000", "--out", str(tmp_path)]
    line = _fails(capsys, dagger.main, argv, "--labels", "memory")
    assert "1.0 GiB" in line or "1024 MiB" in line
    dagger.check_memory(dict(dagger.SIZES["tiny"]), 1, 200, 100)  # no exit


def _record(folder: Path, name: str, sr, curve=True, **config) -> None:
    config = {"size": "default", "encoder": "mlp", "labels": 1, "seed": 0, **config}
    results: dict = {"final": {"mean": {"SR": sr}}}
    if curve:
        results["curve"] = [{"samples": 100}]
    (folder / f"{name}.json").write_text(json.dumps({"config": config, "results": results}))


def test_dagger_report_on_partial_records(tmp_path, capsys):
    """A record without its curve counts (its labels unknown, '-' where none is known); one
    with SR null (a non-finite value) is left out, with a line naming it."""
    from lab.diagnostics import dagger

    _record(tmp_path, "dagger-s0", 0.2, curve=False)
    _record(tmp_path, "dagger-s1", None, seed=1)
    _record(tmp_path, "dagger-s2", 0.3, curve=False, seed=2)
    rows = dagger.report(tmp_path)["arms"]
    assert [r["val_SR"] for r in rows] == [[0.2, 0.3]]
    assert rows[0]["labels"] == []
    err = capsys.readouterr().err
    assert "dagger-s1.json" in err and "SR" in err and "None" in err
    assert "| - |" in (tmp_path / "README.md").read_text()


def test_dagger_report_names_a_missing_folder_as_missing(tmp_path, capsys):
    from lab.diagnostics import dagger

    missing = tmp_path / "not-there"
    line = _fails(capsys, dagger.main, ["--report", str(missing)], str(missing), "no such folder")
    assert "default size" not in line
    _fails(capsys, dagger.main, ["--report", str(tmp_path)], "no DAgger record")
    (tmp_path / "dagger-bad.json").write_text(json.dumps({"config": {}, "results": {}}))
    _fails(capsys, dagger.main, ["--report", str(tmp_path)], "dagger-bad.json", "not a DAgger")


def test_dagger_report_leaves_out_a_non_finite_sr_as_it_does_null(tmp_path, capsys):
    """A record written by `json.dumps` holds a non-finite score as NaN, not null: the report
    leaves it out with the same line instead of averaging NaN into the arm; a NaN score with
    nobody observed is '-' (not measured), as null is."""
    from lab.diagnostics import dagger

    _record(tmp_path, "dagger-s0", 0.2)
    _record(tmp_path, "dagger-s1", float("nan"), seed=1)
    _record(tmp_path, "dagger-s2", 0.4, seed=2)
    blind = json.loads((tmp_path / "dagger-s2.json").read_text())
    blind["results"]["final"]["mean"]["SR_blind"] = float("inf")
    (tmp_path / "dagger-s2.json").write_text(json.dumps(blind))
    rows = dagger.report(tmp_path)["arms"]
    assert [r["val_SR"] for r in rows] == [[0.2, 0.4]]
    assert rows[0]["mean"] == pytest.approx(0.3)
    assert rows[0]["val_SR_blind"] == [None, None]
    err = capsys.readouterr().err
    assert "skipped" in err and "dagger-s1.json" in err and "nan" in err
    assert "nan" not in (tmp_path / "README.md").read_text()


def _scenarios(root: Path) -> Path:
    """A scenarios folder of the authors' layout: 205 tasks of random people."""
    import numpy as np

    from mpcpearl_jax.envs.restaurant import scenarios as sc

    (root / sc.MAIN_FILE).parent.mkdir(parents=True)
    people = np.random.default_rng(0).uniform(-4.5, 4.5, size=(205, 2, 81, 6))
    np.save(root / sc.MAIN_FILE, people)
    return root


def test_fallback_runs_inputs_are_one_line_before_the_rollout(tmp_path, capsys):
    """lab.diagnostics.fallback_runs: a scenarios folder that is not there, a task index outside
    the scenarios (999 was an IndexError, -1 silently the last task), a bad --set and an --out
    that cannot be written (found only after the rollout) are each one line naming the flag."""
    from lab.diagnostics import fallback_runs

    data = _scenarios(tmp_path / "data")
    out = tmp_path / "rec" / "fallback-runs.json"
    afile = tmp_path / "afile"
    afile.write_text("x")

    def fails(argv: list[str], *names: str) -> str:
        return _fails(capsys, fallback_runs.main, argv, *names)

    ok = ["--scenarios", str(data), "--out", str(out)]
    fails(["--scenarios", str(tmp_path / "none"), "--tasks", "0", "--out", str(out)], "--scenarios")
    fails([*ok, "--tasks", "0", "999"], "--tasks 999", "0-204")
    fails([*ok, "--tasks", "-1"], "--tasks -1", "0-204")
    fails([*ok, "--tasks", "0", "--set", "nosuch=1"], "--set nosuch=1", "nosuch")
    argv = ["--scenarios", str(data), "--tasks", "0", "--out"]
    fails([*argv, str(afile / "x.json")], "--out", "a file is where a folder should be")
    fails([*argv, str(tmp_path)], "--out", "a folder")
    fails([*argv, f"{tmp_path / 'new'}/"], "--out", "a folder")  # it became a file 'new'
    assert not out.exists() and not (tmp_path / "new").is_file() and afile.read_text() == "x"
