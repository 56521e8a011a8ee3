"""The lab diagnostics' outputs: every setting in a record's name (a tiny run never replaces a
full-size record), --out and --threads checked before anything runs."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from lab import harness
from lab.diagnostics import crowd_cause, dagger, imitation, shield

DIAGNOSTICS = {
    "dagger": dagger,
    "crowd_cause": crowd_cause,
    "shield": shield,
    "imitation": imitation,
}


def _dagger_args(**kw) -> argparse.Namespace:
    args = dict(relative=True, sorted=True, encoder="mlp", forecast=0, stride=1, labels=1, seed=0)
    args.update(presence=False)
    args.update(tiny=False, full=False, rounds=None, hidden="128,128,128", run=dagger.DEFAULT_RUN)
    return argparse.Namespace(**{**args, **kw})


def test_dagger_names_its_record_by_size_rounds_hidden_and_run() -> None:
    """`--tiny`, `--rounds`, `--hidden` and `--run` were not in the record's name: a tiny run into
    the folder of the full-size records replaced one (SR 0.52 by 0.0)."""
    name = lambda **kw: dagger.record_name(_dagger_args(**kw))  # noqa: E731
    assert name() == "dagger-relative-sorted"  # the committed records' names stand
    assert name(full=True) == "dagger-relative-sorted"  # --full is the default size
    assert name(rounds=12, hidden="128, 128,128") == "dagger-relative-sorted"
    assert name(tiny=True) == "dagger-relative-sorted-tiny"
    assert name(tiny=True, seed=2) == "dagger-relative-sorted-tiny-seed2"
    assert name(rounds=5) == "dagger-relative-sorted-rounds5"
    assert name(hidden="64,64") == "dagger-relative-sorted-hidden64x64"
    assert name(run=Path("runs/mine")) == "dagger-relative-sorted-run-mine"
    assert name(presence=True) == "dagger-relative-sorted-presence"
    assert (
        len({name(), name(tiny=True), name(rounds=5), name(hidden="64"), name(run=Path("x"))}) == 5
    )


def test_the_other_diagnostics_name_their_tiny_and_full_records_apart() -> None:
    assert harness.record_name("shield", "default") == "shield"
    assert harness.record_name("shield", "tiny") == "shield-tiny"
    assert harness.record_name("shield", "full") == "shield-full"
    assert harness.record_name("crowd_cause", "default", delay=(12, 12)) == "crowd_cause"
    assert harness.record_name("crowd_cause", "tiny", delay=(6, 12)) == "crowd_cause-tiny-delay6"
    sel = harness.record_name("imitation", "default", select_seed=(3, 0))
    assert sel == "imitation-select-seed3"
    long = harness.record_name("x", "default", runs=([Path(f"r{i}" * 9) for i in range(9)], []))
    assert len(long) < 30


def _record(folder: Path, name: str, size: str, seed: int, sr: float, **config) -> None:
    config = {"size": size, "encoder": "mlp", "labels": 1, "seed": seed, **config}
    results = {"curve": [{"samples": 100}], "final": {"mean": {"SR": sr}}}
    (folder / f"{name}.json").write_text(json.dumps({"config": config, "results": results}))


def test_dagger_report_names_the_records_it_leaves_out(tmp_path: Path, capsys) -> None:
    """The report left the tiny records out without saying so; records of other rounds or hidden
    sizes are arms of their own, not another seed's value silently replaced."""
    _record(tmp_path, "dagger", "default", 0, 0.5)
    _record(tmp_path, "dagger-seed1", "default", 1, 0.4)
    _record(tmp_path, "dagger-tiny", "tiny", 0, 0.0)
    _record(tmp_path, "dagger-hidden64", "default", 0, 0.3, hidden=[64])
    _record(tmp_path, "dagger-rounds5", "full", 0, 0.2, rounds=5)
    rows = {r["arm"]: r for r in dagger.report(tmp_path)["arms"]}
    assert rows["mlp"]["val_SR"] == [0.5, 0.4]
    assert rows["mlp, hidden 64"]["val_SR"] == [0.3]
    assert rows["mlp, 5 rounds"]["val_SR"] == [0.2]
    assert (
        "left out 1 record(s) not of the default size: dagger-tiny.json" in capsys.readouterr().out
    )


@pytest.mark.parametrize("module", sorted(DIAGNOSTICS))
def test_diagnostic_out_and_threads_are_checked_before_it_runs(module, tmp_path, capsys) -> None:
    """--out on a regular file ran the whole diagnostic (28 minutes for DAgger) and then died
    with a FileExistsError traceback; --threads -1 pinned all cores but the last, 0 meant all,
    more than the cores was a ValueError traceback. Each is now one line, exit 2, at once."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    main = DIAGNOSTICS[module].main
    cores = harness.machine.available_cores()
    cases = [
        (["--out", str(afile)], f"error: --out {afile}: not writable (a file is where a folder"),
        (["--out", str(afile / "sub")], f"error: --out {afile / 'sub'}: not writable"),
        (["--threads", "-1"], f"error: --threads -1: this process may use 1 to {cores} cores"),
        (["--threads", "0"], f"error: --threads 0: this process may use 1 to {cores} cores"),
        (["--threads", str(cores + 3)], f"error: --threads {cores + 3}: this process may use"),
    ]
    for argv, line in cases:
        with pytest.raises(SystemExit) as e:
            main(["--tiny", *argv])
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and err.startswith(line) and "\n" not in err, (argv, err)
    assert afile.read_text() == "x"


def test_configure_threads_refuses_fewer_than_one_core() -> None:
    for n in (-1, 0):
        with pytest.raises(ValueError, match=f"threads {n}: must be at least 1"):
            harness.machine.configure_threads(n)


def test_fallback_runs_never_replaces_a_record_of_other_settings(tmp_path, capsys) -> None:
    """`lab.diagnostics.fallback_runs` writes to one file (by default the committed record): a
    run with other --tasks or --set replaced it silently once its rollout ended. Such a record
    is refused before the rollout, one line naming the file and --overwrite; the same settings,
    or --overwrite, may write."""
    import shutil

    from lab.diagnostics import fallback_runs

    committed = Path(__file__).resolve().parents[1] / "results/mpc/convergence/fallback-runs.json"
    record = tmp_path / "fallback-runs.json"
    shutil.copyfile(committed, record)
    before = record.read_bytes()
    absent = tmp_path / "absent"  # no rollout, whatever the check says
    for argv, what in (
        (["--tasks", "150"], "(tasks, mpc)"),
        (["--tasks", *map(str, json.loads(before)["tasks"])], "(mpc)"),
    ):
        with pytest.raises(SystemExit) as e:
            fallback_runs.main([*argv, "--scenarios", str(absent), "--out", str(record)])
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and "\n" not in err, err
        assert err == (
            f"error: --out {record}: holds a record made with other settings {what}; choose "
            "another --out, or add --overwrite to replace it"
        )
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(SystemExit):
        fallback_runs.main(["--tasks", "1", "--out", str(tmp_path / "list.json")])
    assert "(not a record of this diagnostic)" in capsys.readouterr().err
    assert record.read_bytes() == before
    old = json.loads(before)
    assert fallback_runs._other_record(record, old["tasks"], old["mpc"], False) is None
    assert fallback_runs._other_record(record, [150], old["mpc"], True) is None
    assert fallback_runs._other_record(tmp_path / "new.json", [150], {}, False) is None
