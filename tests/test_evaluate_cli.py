"""`python -m experiments.evaluate`: committed runs (results/) on every split, both envs, GP-MPC
through the same code path, and one-line errors."""

import json
from pathlib import Path

import pytest
from PIL import Image

from mpcpearl_jax.cli.evaluate import UsageError, main, parse_indices
from mpcpearl_jax.evaluation import runners
from mpcpearl_jax.mpc.config import MPCConfig

ROOT = Path(__file__).resolve().parents[1]
RESTAURANT_RUN = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2"
SIDEWALK_RUN = ROOT / "results" / "sidewalk" / "mpc-pearl-eps0.2"
ZARA = ROOT.parent / "shared" / "data" / "crowds_zara01.txt"
needs_zara = pytest.mark.skipif(not ZARA.is_file(), reason="UCY Zara 01 file not available")
METRICS = {"SR", "TT", "CFR", "SPL", "MGD", "return"}


def _record(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


def _frames(path: Path) -> int:
    with Image.open(path) as im:
        return im.n_frames


def test_policy_on_the_whole_test_split_matches_the_runs_results(tmp_path, capsys):
    assert main([str(RESTAURANT_RUN), "--out", str(tmp_path), "--figures", "none"]) == 0
    rec = _record(tmp_path)
    saved = json.loads((RESTAURANT_RUN / "results.json").read_text())["test_adapt"]
    for k in METRICS:
        assert rec["metrics"][k] == pytest.approx(saved[k], rel=1e-5, abs=1e-5), k
    assert rec["tasks"] == list(range(24)) and rec["episodes"] == 3
    assert len(rec["per_task"]["SR"]) == 1 and len(rec["per_task"]["SR"][0]) == 24
    table = capsys.readouterr().out
    assert "| SR |" in table and "| 23 |" in table
    # every episode ends one way: success, a contact (first with a person or a static obstacle),
    # or out of time; contacts agree with CFR
    f = rec["failures"]
    assert f["episodes"] == 24 and f["success"] == round(24 * rec["metrics"]["SR"])
    assert f["success"] + f["contact"] + f["timeout"] == 24
    assert f["contact_person"] + f["contact_static"] == f["contact"]
    assert f["contact"] == round(24 * (1 - rec["metrics"]["CFR"]))
    assert f"{f['success']} reached the goal without contact" in table


@pytest.mark.slow  # 24 tasks of 3 episodes: half a minute on 2 cores
def test_a_run_of_a_retired_option_evaluates_as_recorded(tmp_path):
    """A committed run trained with CrossQ critics (an option since removed: its network.json
    still names `crossq`) loads, and its validation tasks of task seed 1 score what its
    committed record says (docs/extensions.md, Removed options)."""
    run = ROOT / "results" / "restaurant" / "screen" / "crossq-s0"
    assert json.loads((run / "network.json").read_text())["crossq"] is True
    argv = [str(run), "--split", "val", "--task-seed", "1", "--figures", "none"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    rec = _record(tmp_path)
    saved = json.loads((run / "eval/policy-val-seeds1-8/results.json").read_text())
    saved = next(r for r in saved["records"] if r["task_seed"] == 1)
    assert rec["tasks"] == saved["tasks"]
    for k in METRICS:
        assert rec["metrics"][k] == pytest.approx(saved["metrics"][k], rel=1e-5, abs=1e-5), k


@pytest.mark.parametrize("split", ["val", "ood", "train"])
def test_policy_on_each_split(tmp_path, split):
    # 24 tasks, as in the test split: the same program, compiled once
    argv = [str(RESTAURANT_RUN), "--split", split, "--tasks", "0-23", "--figures", "0,5"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    rec = _record(tmp_path)
    assert rec["split"] == split and rec["tasks"] == list(range(24))
    assert set(rec["metrics"]) == METRICS
    assert (tmp_path / f"trajectory_{split}0.png").is_file()
    assert (tmp_path / f"trajectory_{split}5.png").is_file()


def test_a_full_disk_while_writing_a_figure_names_the_figure(tmp_path, capsys, monkeypatch):
    """A full disk during the figures (after results.json): "[Errno 28] No space left on
    device", naming no file. The line names the figure and says results.json was written; no
    partial figure is left."""
    import errno
    import os

    import mpcpearl_jax.envs

    def full_disk(env_name, path, *args, **kwargs):
        Path(path).write_bytes(b"\x89PNG partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as a write() raises it

    monkeypatch.setattr(mpcpearl_jax.envs, "save_trajectory", full_disk)
    argv = [str(RESTAURANT_RUN), "--tasks", "0", "--figures", "0", "--out", str(tmp_path)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    png = tmp_path / "trajectory_test0.png"
    assert err == (
        f"error: {png}: cannot write (No space left on device); {tmp_path / 'results.json'} was "
        "written, this figure was not"
    )
    assert (tmp_path / "results.json").is_file() and not png.exists()


@pytest.mark.slow  # (~13 s) pooling is also checked in the GrBAL command's test
def test_task_seeds_pool_the_splits_of_several_task_set_seeds(tmp_path, capsys, monkeypatch):
    evaluators: dict = {}
    monkeypatch.setattr(runners, "_EVALUATORS", evaluators)
    singles = []
    for ts in (1, 2):
        out = tmp_path / f"seed{ts}"
        argv = [str(RESTAURANT_RUN), "--split", "val", "--task-seed", str(ts), "--tasks", "0-5"]
        assert main([*argv, "--figures", "none", "--out", str(out)]) == 0
        singles.append(_record(out))
    assert singles[0]["per_task"]["return"] != singles[1]["per_task"]["return"]  # fresh tasks
    argv = [str(RESTAURANT_RUN), "--split", "val", "--task-seeds", "1-2", "--tasks", "0-5"]
    assert main([*argv, "--out", str(tmp_path / "pool")]) == 0
    rec = _record(tmp_path / "pool")
    assert rec["task_seeds"] == [1, 2] and rec["num_tasks"] == 12
    for k in METRICS:
        values = [v for r in singles for v in r["per_task"][k][0]]
        assert rec["pooled"][k]["mean"] == pytest.approx(sum(values) / 12, rel=1e-6, abs=1e-6)
        assert rec["pooled"][k]["per_task_seed"] == pytest.approx(
            [r["metrics"][k] for r in singles], rel=1e-5, abs=1e-5
        )
    ret = [v for r in singles for v in r["per_task"]["return"][0]]
    mean = sum(ret) / 12
    se = (sum((v - mean) ** 2 for v in ret) / 11) ** 0.5 / 12**0.5
    assert rec["pooled"]["return"]["se"] == pytest.approx(se, rel=1e-6)
    printed = capsys.readouterr().out
    assert "task seeds 1-2 (12 tasks)" in printed and "episodes 12:" in printed
    for k in ("success", "contact", "contact_person", "reached_goal_after_contact", "timeout"):
        assert rec["failures"][k] == sum(r["failures"][k] for r in singles), k
    # four task sets, one program: the protocol was traced and compiled once
    assert len(evaluators) == 1
    assert next(iter(evaluators.values()))._cache_size() == 1
    assert main([str(RESTAURANT_RUN), "--task-seeds", "1-2", "--task-seed", "3"]) == 2
    assert main([str(RESTAURANT_RUN), "--task-seeds", "x"]) == 2
    assert "--task-seeds 'x'" in capsys.readouterr().err


@pytest.mark.slow  # the online evaluation with its GIF (~17 s); both are tested fast on their own
def test_online_with_animation(tmp_path):
    argv = [str(RESTAURANT_RUN), "--online", "--tasks", "3", "--animate", "--out", str(tmp_path)]
    assert main(argv) == 0
    rec = _record(tmp_path)
    assert rec["protocol"] == "online" and rec["episodes"] == 1 and rec["seeds"] == [0]
    gif = tmp_path / "episode_test3.gif"
    assert _frames(gif) == 81 and gif.stat().st_size < 400_000


def test_default_out_is_inside_the_run(tmp_path):
    import shutil

    run = tmp_path / "run"
    run.mkdir()
    for name in ("config.json", "policy.msgpack"):  # all that a policy evaluation needs
        shutil.copy(RESTAURANT_RUN / name, run / name)
    assert main([str(run), "--figures", "none"]) == 0
    rec = _record(run / "eval" / "policy-test")
    assert rec["episodes"] == 3 and rec["protocol"] == "after 2 adaptation episode(s)"


@pytest.mark.slow  # (~11 s); the GP-MPC command: test_cli
def test_gp_mpc_without_a_run(tmp_path):
    assert main(["--controller", "gp-mpc", "--tasks", "0", "--out", str(tmp_path)]) == 0
    rec = _record(tmp_path)
    assert rec["label"] == "GP-MPC" and rec["run"] is None and rec["mpc_share"] > 0.5
    assert rec["mpc_status"].get("solved", 0) > 0
    assert (tmp_path / "trajectory_test0.png").is_file()


@pytest.mark.slow
def test_gp_mpc_on_a_runs_tasks_and_policy_with_mpc(tmp_path):
    out = tmp_path / "g"
    argv = [str(RESTAURANT_RUN), "--controller", "gp-mpc", "--split", "val", "--tasks", "0"]
    assert main([*argv, "--animate", "--out", str(out)]) == 0
    # the run's MPC settings, plus the defaults of fields added after it was trained
    recorded = json.loads((RESTAURANT_RUN / "config.json").read_text())["mpc"]
    assert _record(out)["mpc"] == {**MPCConfig().to_dict(), **recorded}
    assert _frames(out / "episode_val0.gif") == 81
    out = tmp_path / "p"
    argv = [str(RESTAURANT_RUN), "--controller", "policy+mpc", "--eps", "1", "--tasks", "0"]
    assert main([*argv, "--animate", "--out", str(out)]) == 0
    rec = _record(out)
    assert rec["eps"] == 1.0 and rec["mpc_share"] > 0
    assert _frames(out / "episode_test0.gif") == 81


@needs_zara
@pytest.mark.parametrize("split", ["test", "ood", "train"])
def test_sidewalk_run_on_each_split(tmp_path, split):
    argv = [str(SIDEWALK_RUN), "--split", split, "--online", "--tasks", "0"]
    argv += ["--data", str(ZARA), "--out", str(tmp_path)]
    if split == "test":
        argv.append("--animate")
    assert main(argv) == 0
    rec = _record(tmp_path)
    assert rec["env"] == "sidewalk" and rec["split"] == split and set(rec["metrics"]) == METRICS
    if split == "test":  # 251 steps shown as every third one (and the last)
        assert _frames(tmp_path / "episode_test0.gif") == 85


@needs_zara
def test_sidewalk_has_no_val_split(tmp_path, capsys):
    argv = [str(SIDEWALK_RUN), "--split", "val", "--data", str(ZARA), "--out", str(tmp_path)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: sidewalk --split val") and "\n" not in err


def _error(argv, capsys) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    return err


def test_errors_are_one_line(tmp_path, capsys):
    assert "is this a run directory" in _error([str(tmp_path)], capsys)
    assert "no such directory" in _error([str(tmp_path / "nope")], capsys)
    assert "needs a run directory" in _error([], capsys)
    err = _error([str(SIDEWALK_RUN), "--data", str(tmp_path / "zara.txt")], capsys)
    assert "zara.txt does not exist" in err
    assert "out of range" in _error([str(RESTAURANT_RUN), "--tasks", "30"], capsys)
    assert "seed(s)" in _error([str(RESTAURANT_RUN), "--seed-index", "3"], capsys)
    assert "GP-MPC does not adapt" in _error(["--controller", "gp-mpc", "--online"], capsys)
    assert "policy+mpc" in _error(["--controller", "gp-mpc", "--eps", "0.5"], capsys)
    assert "MPCConfig" in _error(["--controller", "gp-mpc", "--set", "nope=1"], capsys)
    (tmp_path / "config.json").write_text((RESTAURANT_RUN / "config.json").read_text())
    assert "policy.msgpack" in _error([str(tmp_path)], capsys)


def test_bad_split_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as e:
        main([str(RESTAURANT_RUN), "--split", "holdout"])
    assert e.value.code == 2
    assert "invalid choice: 'holdout'" in capsys.readouterr().err


def test_parse_indices():
    assert parse_indices("all", 3, "--tasks") == [0, 1, 2]
    assert parse_indices("none", 3, "--tasks") == []
    assert parse_indices("4,0-2,2", 5, "--tasks") == [0, 1, 2, 4]
    with pytest.raises(UsageError, match="expected numbers"):
        parse_indices("a-b", 5, "--tasks")


def test_long_index_lists_and_huge_seed_ranges_are_short_errors(tmp_path, capsys):
    """`--tasks 0-1000` used to list 977 indices in its error; `--task-seeds 0-100000` had no
    cap (each seed is a whole evaluation)."""
    from mpcpearl_jax.cli.evaluate import MAX_TASK_SEEDS, UsageError, main, parse_indices

    with pytest.raises(UsageError, match=r"task\(s\) \[24, 25, 26\] and 974 more out of range"):
        parse_indices("0-1000", 24, "--tasks")
    run = str(Path(__file__).resolve().parents[1] / "results/restaurant/main-default")
    argv = [run, "--split", "val", "--task-seeds", "0-100000", "--out", str(tmp_path / "e")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"100001 task sets; at most {MAX_TASK_SEEDS}" in err and len(err.splitlines()) == 1


class _BrokenStdout:
    """A standard output that breaks as `| head -1` (after its first line) or `> /dev/full`."""

    def __init__(self, error: OSError, lines: int = 0) -> None:
        self.error, self.lines, self.text = error, lines, ""

    def write(self, text: str) -> int:
        if self.text.count("\n") >= self.lines:
            raise self.error
        self.text += text
        return len(text)

    def flush(self) -> None:
        if self.text.count("\n") > self.lines:
            raise self.error


@pytest.mark.parametrize("case", ["head", "full"])
def test_a_broken_stdout_loses_no_results(case, tmp_path, capsys, monkeypatch):
    """The table was printed before results.json was written: `| head -1` ended the command with
    a BrokenPipeError traceback and an empty folder, `> /dev/full` with an OSError. Now the files
    are written first, and a broken stdout is one line on stderr, exit code 2."""
    import errno
    import sys

    error = BrokenPipeError(errno.EPIPE, "Broken pipe")
    if case == "full":
        error = OSError(errno.ENOSPC, "No space left on device")
    stdout = _BrokenStdout(error, lines=1 if case == "head" else 0)
    argv = [str(RESTAURANT_RUN), "--tasks", "0", "--figures", "0", "--out", str(tmp_path)]
    with monkeypatch.context() as m:
        m.setattr(sys, "stdout", stdout)
        code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err, err
    assert (
        err == f"error: standard output: {error.strerror}; results.json and the figures are written"
    )
    assert _record(tmp_path)["tasks"] == [0] and (tmp_path / "trajectory_test0.png").is_file()
    assert stdout.text.startswith("[evaluate]") if case == "head" else stdout.text == ""
    if case == "full":  # the pooled record of --task-seeds: written, then printed
        with monkeypatch.context() as m:
            m.setattr(sys, "stdout", _BrokenStdout(error))
            argv = ["--task-seeds", "1", "--tasks", "0", "--out", str(tmp_path / "pooled")]
            code = main([str(RESTAURANT_RUN), *argv])
        assert code == 2 and _record(tmp_path / "pooled")["task_seeds"] == [1]
