"""End-to-end smoke runs of the README's other commands, at tiny sizes."""

import json

import pytest


def test_sidewalk_cli_with_mpc_infusion(tmp_path):
    """`python -m experiments.sidewalk` (synthetic crowd) with eps > 0: the MPC really acts."""
    from mpcpearl_jax.cli.train import main

    out = tmp_path / "s"
    argv = [
        "--preset",
        "smoke",
        "--eps",
        "0.5",
        "--iterations",
        "1",
        "--out",
        str(out),
        "--no-progress",
        "--set",
        "train.initial_episodes=1",
        "--set",
        "train.tasks_per_iteration=2",
    ]
    assert main("sidewalk", argv, online_eval=True, mpc={"v_max": None}) == 0
    log = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert log[0]["mpc_rows"] > 0 and log[0]["train_mpc_share"] > 0
    assert log[0]["mpc_host_s"] > 0
    res = json.loads((out / "results.json").read_text())
    assert res["env"] == "sidewalk" and "SR" in res["test_online"]
    assert res["config"]["online_eval"] is True
    assert {"cpu_count", "cores_available", "jax"} <= set(res["machine"])


def test_sidewalk_cli_rejects_missing_data(tmp_path, capsys):
    from mpcpearl_jax.cli.train import main

    assert main("sidewalk", ["--preset", "smoke", "--data", str(tmp_path / "nope.txt")]) == 2
    assert "nope.txt" in capsys.readouterr().err


def test_gp_mpc_cli(tmp_path):
    from experiments import gp_mpc

    gp_mpc.main(
        ["--env", "restaurant", "--split", "test", "--max-tasks", "2", "--out", str(tmp_path)]
    )
    rec = json.loads((tmp_path / "restaurant_test_tasks0-2.json").read_text())
    assert set(rec["metrics"]) >= {"SR", "TT", "CFR", "SPL", "MGD"}
    assert rec["status"].get("solved", 0) > 0


def test_gp_mpc_preset_takes_that_presets_mpc():
    """`--preset default` runs the expert the learned presets train with (2 QPs and the
    unsafe-plan recovery; it needed five --set flags); without it, the `paper` preset's MPC (the
    SQP to convergence); --set still changes a field on top."""
    from experiments.gp_mpc import mpc_settings
    from mpcpearl_jax.config import preset
    from mpcpearl_jax.mpc import MPCConfig

    teacher = mpc_settings("restaurant", "default", [])
    assert teacher == preset("default").mpc
    assert teacher.sqp_iters == 2 and teacher.unsafe_recovery
    assert mpc_settings("restaurant", "paper", []) == MPCConfig()
    assert mpc_settings("restaurant", "default", ["alpha=0.9"]) == teacher.replace(alpha=0.9)
    assert mpc_settings("sidewalk", "default", []).v_max != teacher.v_max  # the family's cap


def test_gp_mpc_names_its_record_by_its_settings(tmp_path):
    """Another --preset, --seed, --sample-seed, --set, --tasks or --max-tasks into the same --out
    named the same record (`ENV_SPLIT.json`) and replaced the earlier one; each now has a name of
    its own, and the defaults keep the committed records' names."""
    from experiments import gp_mpc

    def name(stop=24, **kw):
        args = {"env": "restaurant", "split": "test", "tasks": None, "preset": "paper"}
        args.update(seed=0, sample_seed=0, set=[], scenarios=None)
        return gp_mpc.record_name(gp_mpc.argparse.Namespace(**{**args, **kw}), 0, stop, 24)

    assert name() == "restaurant_test.json"
    assert name(scenarios="x") == "restaurant_test.json"
    names = {
        name(preset="default"),
        name(seed=3),
        name(sample_seed=1),
        name(set=["v_max=5.0"]),
        name(set=["alpha=0.9"]),
        name(stop=2),  # --max-tasks 2
        name(tasks="0:24"),
        name(preset="default", seed=3),
    }
    assert len(names) == 8 and "restaurant_test.json" not in names
    assert name(set=["v_max=5.0"]) == "restaurant_test_set-v_max=5.0.json"
    assert name(seed=3, scenarios="x") == "restaurant_test.json"  # no seed with scenarios
    assert len(name(set=[f"alpha=0.{i}" for i in range(20)])) < 60
    # tasks that are not consecutive (--tasks 0,3,5) are named by their numbers
    ids = gp_mpc.argparse.Namespace(
        **{
            **dict(env="restaurant", split="test", tasks="0,3,5"),
            **dict(preset="paper", seed=0, sample_seed=0, set=[]),
        },
        scenarios=None,
    )
    assert gp_mpc.record_name(ids, 0, 6, 24, [0, 3, 5]) == "restaurant_test_tasks0+3+5.json"
    assert gp_mpc.record_name(ids, 0, 2, 24, [0, 1]) == "restaurant_test_tasks0-2.json"


def test_gp_mpc_never_replaces_a_record_of_other_settings(tmp_path, capsys):
    """A record of the same name made with other settings (another --scenarios or --data) is
    refused before the rollout, in one line naming the file and --overwrite; nothing changes."""
    from experiments import gp_mpc

    out = tmp_path / "g"
    out.mkdir()
    old = out / "restaurant_test.json"
    old.write_text(json.dumps({"env": "restaurant", "split": "test", "scenarios": {"x": 1}}))
    before = old.read_text()
    assert gp_mpc.main(["--split", "test", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {old}: holds a record made with other settings") and (
        "--overwrite" in err and "\n" not in err
    )
    argv = ["--split", "test", "--set", "alpha=0.9", "--out", str(out)]
    (out / "restaurant_test_set-alpha=0.9.json").write_text("[1, 2]")  # not a record
    assert gp_mpc.main(argv) == 2
    assert "not a record of this command" in capsys.readouterr().err
    assert old.read_text() == before and sorted(p.name for p in out.iterdir()) == [
        "restaurant_test.json",
        "restaurant_test_set-alpha=0.9.json",
    ]


def _stub_gp_mpc_rollout(monkeypatch, seen: list) -> None:
    """The GP-MPC rollout replaced by a straight line from start to goal per task (no MPC, no
    compilation): what is tested is what the command writes and prints around it."""
    import numpy as np

    from mpcpearl_jax.api import evaluate as api

    def run_setup(s, eval_seed, episodes=None, online=False):
        seen.append(s.mpc)
        start, goal = np.asarray(s.tasks.start)[:, :2], np.asarray(s.tasks.goal)
        w = np.linspace(0.0, 1.0, s.env_config.horizon + 1)[None, :, None]
        steps = (1, len(start), s.env_config.horizon)
        result = {
            "position": (start[:, None] + w * (goal - start)[:, None])[None],
            "collision": np.zeros(steps, bool),
            "in_goal": np.zeros(steps, bool),
        }
        stats = {"status": {"solved": 1}, "reasons": {}, "sqp_stops": {}, "starts": {}}
        return {"wall_s": 0.1}, result, {**stats, "solve_s": [0.01, 0.02]}

    monkeypatch.setattr(api, "run_setup", run_setup)


def test_gp_mpc_runs_of_other_settings_keep_their_figures(tmp_path, capsys, monkeypatch):
    """The trajectory figure was named by family, split and task only: a run with another
    --preset into the same --out kept its record apart but replaced the earlier run's figure. It
    is named after its record now (the default's name unchanged). The second run's standard
    output breaks after one line (`| head -1`): both files are written first, then one line on
    stderr, exit 2."""
    import errno
    import sys

    from test_evaluate_cli import _BrokenStdout

    from experiments import gp_mpc

    seen: list = []
    _stub_gp_mpc_rollout(monkeypatch, seen)
    out = tmp_path / "g"
    assert gp_mpc.main(["--split", "test", "--out", str(out)]) == 0
    first = (out / "restaurant_test_task0.png").read_bytes()
    capsys.readouterr()
    stdout = _BrokenStdout(BrokenPipeError(errno.EPIPE, "Broken pipe"), lines=1)
    with monkeypatch.context() as m:
        m.setattr(sys, "stdout", stdout)
        argv = ["--split", "test", "--max-tasks", "2", "--preset", "default", "--out", str(out)]
        code = gp_mpc.main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2 and err == (
        "error: standard output: Broken pipe; the record and the figure are written"
    )
    assert stdout.text.startswith("GP-MPC on restaurant/test: 2 tasks (0 to 1)")
    assert sorted(p.name for p in out.iterdir()) == [
        "restaurant_test.json",
        "restaurant_test_task0.png",
        "restaurant_test_tasks0-2_preset-default.json",
        "restaurant_test_tasks0-2_preset-default_task0.png",
    ]
    assert (out / "restaurant_test_task0.png").read_bytes() == first
    assert len(seen) == 2 and seen[0] != seen[1]  # the two presets' MPC settings
    record = json.loads((out / "restaurant_test_tasks0-2_preset-default.json").read_text())
    assert record["preset"] == "default" and record["tasks"] == [0, 2]
    assert gp_mpc.figure_path(out / "restaurant_test.json", 3) == out / "restaurant_test_task3.png"


def test_compare_names_the_runs_with_labels(tmp_path, capsys):
    """`lab.compare --labels`: one name per run in the figure and summary; a wrong count
    is a one-line error."""
    from lab import compare

    runs = ["results/restaurant/mpc-pearl-eps0.2", "results/restaurant/mpc-pearl-eps0.2-paper"]
    out = tmp_path / "cmp"
    assert compare.main([*runs, "--out", str(out), "--labels", "headline, paper alg."]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [r["label"] for r in summary["runs"]] == ["headline", "paper alg."]
    assert "| headline" in (out / "table.md").read_text()
    assert (out / "curves.png").is_file()
    capsys.readouterr()
    assert compare.main([*runs, "--out", str(out), "--labels", "only one"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--labels" in err and "\n" not in err


def test_gp_mpc_tasks_and_max_tasks_are_checked_before_the_rollout(tmp_path, capsys):
    """--tasks (the task syntax of experiments.evaluate: 0,3,5, 0-3, START:STOP), --max-tasks
    and --plot-task out of range or malformed: one line naming the flag, exit 2, nothing
    written."""
    from experiments import gp_mpc

    out = tmp_path / "g"
    cases = [
        (["--tasks", "3:3"], "--tasks '3:3': the range 3:3 is empty"),
        (["--tasks", "a:b"], "--tasks 'a:b': expected numbers like 0,3,5, 0-3"),
        (["--tasks=-1:2"], "--tasks '-1:2': the range -1:2 is empty or negative"),
        (["--tasks", "3-1"], "--tasks '3-1': the range 3-1 is reversed"),
        (["--tasks", "30:40"], "--tasks: task(s) [30, 31, 32] and 7 more out of range"),
        (["--tasks", "0:999999"], "--tasks: task(s) [24, 25, 26] and 999972 more out of range"),
        (["--tasks", "20:25"], "--tasks: task(s) [24] out of range; the split has 24 tasks"),
        (["--preset", "nosuch"], "--preset: unknown preset 'nosuch'"),
        (["--set", "nosuch=1"], "--set nosuch=1: MPCConfig has no field"),
        (["--max-tasks", "0"], "--max-tasks must be positive, got 0"),
        (["--tasks", "0:2", "--plot-task", "5"], "--plot-task 5: not among the tasks run (0 to 1)"),
        (["--tasks", "0,3", "--plot-task", "1"], "--plot-task 1: not among the tasks run (0,3)"),
        (["--split", "nosuch"], "--split 'nosuch': one of train"),
    ]
    for extra, msg in cases:
        assert gp_mpc.main(["--split", "test", *extra, "--out", str(out)]) == 2, extra
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"error: {msg}") and "\n" not in err, (extra, err)
    assert not list(out.glob("*.json"))


def test_an_out_through_a_file_and_a_data_folder_say_what_is_wrong(tmp_path, capsys):
    """--out whose path passes through a regular file said "fix its permissions"; --data given a
    folder said "no such file". Each is now one line that names the real cause."""
    from mpcpearl_jax.cli.train import main

    afile = tmp_path / "afile"
    afile.write_text("")
    assert main("restaurant", ["--preset", "smoke", "--out", str(afile / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"error: {afile / 'run'}: not writable (a file is where a folder should be); choose "
        "another --out"
    )
    assert main("sidewalk", ["--preset", "smoke", "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: --data {tmp_path}: a folder; give a trajectory file in it")
    assert "\n" not in err


@pytest.mark.slow  # (~40 s: three small trainings)
def test_resume_of_a_finished_run_says_so_in_one_line_and_changes_nothing(tmp_path, capsys):
    """--resume of a run that trained all its iterations and wrote results.json: one line that
    it is finished, exit 0, no file touched (it re-ran the final evaluation, rewrote
    results.json and printed "0 iteration(s) ... trained in 0.0 min"). With more iterations it
    trains on."""
    from faults_helpers import small_args

    from mpcpearl_jax.cli.train import main

    run = tmp_path / "run"
    assert main("restaurant", small_args(0.0, run, 1)) == 0
    capsys.readouterr()
    before = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in run.rglob("*") if p.is_file()}
    assert main("restaurant", [*small_args(0.0, run, 1), "--resume"]) == 0
    out = capsys.readouterr().out.strip()
    assert out == (
        f"{run}: finished (1 iteration(s), results.json written); nothing to do (to train it "
        "further: --resume --iterations N, N above 1)"
    )
    after = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in run.rglob("*") if p.is_file()}
    assert after == before
    assert main("restaurant", [*small_args(0.0, run, 2), "--resume"]) == 0
    assert "1 iteration(s) x 3 gradient steps" in capsys.readouterr().out


def test_preset_help_names_the_presets_and_a_removed_one_gets_its_message(capsys):
    """--preset's help names the presets there are (it named the removed cpu-paper and called
    cpu-explore the recipe), and --preset cpu-paper reaches the removed-preset message (argparse's
    choices refused it first)."""
    from mpcpearl_jax.cli.args import parser
    from mpcpearl_jax.cli.train import main
    from mpcpearl_jax.config import PRESETS

    text = " ".join(parser("restaurant").format_help().split())
    assert "cpu-paper" not in text and "recipe: the recommended CPU recipe" in text
    assert "{" + ",".join(sorted(PRESETS)) + "}" in text
    for extra in ([], ["--print-config"]):
        assert main("restaurant", ["--preset", "cpu-paper", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: preset 'cpu-paper' was removed (") and "\n" not in err
    assert main("restaurant", ["--preset", "nope", "--print-config"]) == 2
    assert "unknown preset 'nope'" in capsys.readouterr().err


@pytest.mark.slow  # (~40 s: a 0.2-minute training, then its resume)
def test_resume_of_a_finished_minutes_run_says_so_and_changes_nothing(tmp_path, capsys):
    """The same for a run on a time budget: its budget spent and results.json written,
    --resume with the same --minutes is one line and touches nothing (it re-evaluated and
    rewrote results.json and curve.json)."""
    from faults_helpers import learning_args

    from mpcpearl_jax.cli.train import main

    run = tmp_path / "run"
    assert main("restaurant", learning_args(run, 0.2, 0.1, "--no-progress")) == 0
    capsys.readouterr()
    before = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in run.rglob("*") if p.is_file()}
    assert main("restaurant", [*learning_args(run, 0.2, 0.1, "--no-progress"), "--resume"]) == 0
    assert capsys.readouterr().out.strip() == (
        f"{run}: finished (0.2 minutes of training, results.json written); nothing to do (to "
        "train it further: --resume --minutes M, M above 0.2)"
    )
    after = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in run.rglob("*") if p.is_file()}
    assert after == before
