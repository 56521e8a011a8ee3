"""lab.campaign: a queue of learning runs, one at a time, continued across sessions."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from lab import campaign


@pytest.fixture(autouse=True)
def _idle_machine(monkeypatch):
    """The campaign waits for a quiet machine before wall-clock trainings: tests see one."""
    monkeypatch.setattr(campaign.os, "getloadavg", lambda: (0.0, 0.0, 0.0))


def _write(tmp_path: Path, runs) -> Path:
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"runs": runs}))
    return path


def _run(name="a", results="res/a", evaluate=None):
    r = {"name": name, "argv": ["--preset", "smoke", "--minutes", "0.05"], "results": results}
    if evaluate is not None:
        r["evaluate"] = evaluate
    return r


@pytest.mark.parametrize(
    "runs, match",
    [
        ([], "at least one run"),
        ([{"name": "a"}], r"runs\[0\]: needs"),
        ([_run(), _run()], "unique"),
        ([_run(name="x/y")], "unique folder name"),
        ([{**_run(), "argv": ["--out", "d"]}], "--out"),
        ([{**_run(), "argv": ["--resume"]}], "--resume"),
        ([_run(evaluate=[["--split", "val"]])], "must give --out"),
        ([_run(evaluate="--split val")], "list of argument lists"),
        ([_run(evaluate=[["--nosuch", "--out", "x"]])], "unrecognized arguments: --nosuch"),
        ([_run(evaluate=[["--split", "nosuch", "--out", "x"]])], "invalid choice: 'nosuch'"),
        ([_run(evaluate=[["--shield-margin", "1", "--out", "x"]])], "need --shield"),
        ([{**_run(), "trainer": "ppo"}], "'trainer' must be one of"),
        ([{**_run(), "trainr": "grbal"}], r"unknown key\(s\) \['trainr'\]"),
        ([{**_run(), "evaluat": []}], r"unknown key\(s\) \['evaluat'\]"),
        ([_run(name="..")], "not starting with '.'"),
        ([_run(name=".")], "not starting with '.'"),
        ([{**_run(), "results": ["a"]}], "'results' must be a folder path"),
    ],
)
def test_bad_campaign_files_name_the_entry(tmp_path, runs, match):
    with pytest.raises(ValueError, match=match):
        campaign.load_campaign(_write(tmp_path, runs))
    with pytest.raises(ValueError, match="not a readable JSON"):
        campaign.load_campaign(tmp_path / "missing.json")


def test_states_commands_and_copy(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ev = [["--split", "val", "--out", "{results}/eval/v"]]
    (run,) = campaign.load_campaign(_write(tmp_path, [_run(evaluate=ev)]))
    # the flags read as mpcpearl_jax.evaluate's keyword arguments (defaults left out)
    keywords = {"run": "res/a", "split": "val", "out": "res/a/eval/v"}
    assert [e.arguments for e in run.evaluate] == [keywords]
    assert run.evaluate[0].record == Path("res/a/eval/v/results.json")
    assert campaign.state_of(run) == "new"
    cmds = campaign.commands(run, "new")
    assert cmds[0][1:4] == ["-m", "experiments.restaurant", "--preset"]
    assert cmds[0][-2:] == ["--out", str(campaign.WORK / "a")]
    assert cmds[1][:3] == [sys.executable, "-m", "lab.evaluation"] and len(cmds[1]) == 4
    assert json.loads(cmds[1][3]) == keywords
    # a checkpoint: resumed
    (run.work / "checkpoints" / "5").mkdir(parents=True)
    assert campaign.state_of(run) == "resume"
    assert campaign.commands(run, "resume")[0][-1] == "--resume"
    # interrupted runs write a curve too, but only one stopped on its budget is finished
    (run.work / "curve.json").write_text(json.dumps({"stopped": "interrupted"}))
    assert campaign.state_of(run) == "resume"
    (run.work / "curve.json").write_text(json.dumps({"stopped": "budget"}))
    (run.work / "policy.msgpack").write_bytes(b"p")
    (run.work / ".lock").write_text("")
    (run.work / "eval").mkdir()
    (run.work / "eval" / "x.json").write_text("{}")
    # its record, but the process has not exited 0 (killed writing its last files): resumed
    assert campaign.state_of(run) == "resume"
    (run.work / campaign.TRAINED).write_text("{}")
    assert campaign.state_of(run) == "finished"
    campaign.copy_results(run)
    copied = sorted(p.relative_to(run.results).as_posix() for p in run.results.rglob("*"))
    assert copied == ["campaign.json", "curve.json", "eval", "eval/x.json", "policy.msgpack"]
    assert campaign.state_of(run) == "done"
    assert [c[2] for c in campaign.commands(run, "done")] == ["lab.evaluation"]
    (run.results / "eval" / "v").mkdir()
    (run.results / "eval" / "v" / "results.json").write_text("{}")
    assert campaign.commands(run, "done") == []


def test_dry_run_prints_and_runs_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    path = _write(tmp_path, [_run("a"), _run("b", results="res/b")])
    (tmp_path / "res" / "b").mkdir(parents=True)
    (tmp_path / "res" / "b" / "curve.json").write_text("{}")
    calls = []
    monkeypatch.setattr(campaign, "run_child", lambda cmd: calls.append(cmd) or 0)
    assert campaign.main([str(path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "a: new, 1 process(es)" in out and "b: done" in out and not calls
    assert campaign.main([str(path), "--only", "nosuch"]) == 2


def test_a_failing_run_stops_the_campaign_with_its_code(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    path = _write(tmp_path, [_run("a"), _run("b", results="res/b")])
    calls = []

    def call(cmd):
        calls.append(cmd)
        return 130  # Ctrl-C in the run under way

    monkeypatch.setattr(campaign, "run_child", call)
    assert campaign.main([str(path)]) == 130
    assert len(calls) == 1 and calls[0][0] == sys.executable
    assert "a: experiments.restaurant" in capsys.readouterr().err


def test_grbal_runs_train_with_their_own_command_and_finish_with_their_results(
    tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    ev = [["--split", "val", "--task-seeds", "1-8", "--out", "{results}/eval/v"]]
    entry = {**_run("g", results="res/g", evaluate=ev), "trainer": "grbal"}
    (run,) = campaign.load_campaign(_write(tmp_path, [entry]))
    assert campaign.state_of(run) == "new"
    assert campaign.commands(run, "new")[0][1:3] == ["-m", "experiments.grbal"]
    main = campaign.load_campaign(_write(tmp_path, [{**entry, "trainer": "restaurant"}]))[0]
    assert campaign.commands(main, "new")[0][1:3] == ["-m", "experiments.restaurant"]
    (run.work / "checkpoints" / "3").mkdir(parents=True)
    assert campaign.state_of(run) == "resume"
    (run.work / "policy.msgpack").write_bytes(b"p")
    (run.work / "results.json").write_text("{}")
    assert campaign.state_of(run) == "resume"  # results.json is written before the figures
    (run.work / campaign.TRAINED).write_text("{}")
    assert campaign.state_of(run) == "finished"
    campaign.copy_results(run)
    names = sorted(p.name for p in run.results.iterdir())
    assert names == ["campaign.json", "policy.msgpack", "results.json"]
    assert campaign.state_of(run) == "done"
    assert [c[2] for c in campaign.commands(run, "done")] == ["lab.evaluation"]


def _guarded_child(tmp_path):
    """A child that takes a second to save on SIGINT, then exits 130: (saved, ready, code)."""
    saved, ready = tmp_path / "saved", tmp_path / "ready"
    child = (
        "import signal, sys, time, pathlib\n"
        "def stop(*_):\n"
        "    time.sleep(1.0)\n"
        f"    pathlib.Path({str(saved)!r}).write_text('state')\n"
        "    sys.exit(130)\n"
        "signal.signal(signal.SIGINT, stop)\n"
        f"pathlib.Path({str(ready)!r}).write_text('')\n"
        "time.sleep(60)\n"
    )
    return saved, ready, child


@pytest.mark.parametrize(
    "whole_group, started_ignoring", [(True, False), (False, False), (False, True)]
)
def test_ctrl_c_lets_the_run_under_way_save_before_the_campaign_stops(
    tmp_path, whole_group, started_ignoring
):
    """Ctrl-C (SIGINT to the campaign's process group) or `kill -INT` of the campaign alone:
    the child gets exactly one SIGINT, takes a second to save and exits 130; the campaign waits
    for it (subprocess.call would kill it after 0.25 s) and returns its code. Also when the
    campaign was started with SIGINT ignored, as a shell without job control starts a
    background job (`nohup ... &` in a script)."""
    import os
    import signal
    import subprocess
    import time

    saved, ready, child = _guarded_child(tmp_path)
    # started ignoring: the state a process inherits from a shell's background job (the
    # disposition set before run_child, without a preexec_fn fork beside JAX's threads)
    ignoring = "signal.signal(signal.SIGINT, signal.SIG_IGN); " if started_ignoring else ""
    parent = (
        f"import signal, sys; {ignoring}from lab import campaign; "
        f"sys.exit(campaign.run_child([sys.executable, '-c', {child!r}]))"
    )
    root = Path(__file__).resolve().parents[1]
    p = subprocess.Popen([sys.executable, "-c", parent], cwd=root, start_new_session=True)
    deadline = time.monotonic() + 60
    while not ready.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert ready.exists(), "the child did not start"
    if whole_group:
        os.killpg(p.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
    else:
        os.kill(p.pid, signal.SIGINT)  # the campaign's process only (a job under nohup)
    assert p.wait(timeout=30) == 130
    assert saved.read_text() == "state"


def test_settle_waits_for_the_load_average_and_gives_up_at_its_limit(monkeypatch):
    from mpcpearl_jax.training.budget import LOAD_WARN

    assert campaign.SETTLE_LOAD == LOAD_WARN
    loads = iter([2.0, 1.8, 1.6, 1.2])
    slept = []
    monkeypatch.setattr(campaign.os, "getloadavg", lambda: (next(loads), 0.0, 0.0))
    monkeypatch.setattr(campaign.time, "sleep", slept.append)
    assert campaign.settle(limit_s=100, poll_s=5) == 15 and slept == [5, 5, 5]
    monkeypatch.setattr(campaign.os, "getloadavg", lambda: (3.0, 0.0, 0.0))
    assert campaign.settle(limit_s=12, poll_s=5) == 15  # busy for good: stops after the limit


def test_only_wall_clock_trainings_wait_for_the_load(tmp_path, monkeypatch, capsys):
    """A learning run and a `restaurant` run given --minutes (how seed screens set a time budget)
    wait for the load before they start; a `restaurant` run on an iteration count does not."""
    monkeypatch.chdir(tmp_path)
    timed = {**_run("t", results="res/t"), "trainer": "restaurant"}  # _run's argv: --minutes
    counted = {**timed, "name": "m", "results": "res/m", "argv": ["--preset", "smoke"]}
    runs = [_run("a"), counted, timed]
    path = _write(tmp_path, runs)
    settled, calls = [], []
    monkeypatch.setattr(campaign, "settle", lambda: settled.append(1) or 10.0)
    monkeypatch.setattr(campaign.os, "getloadavg", lambda: (1.0, 0.0, 0.0))
    monkeypatch.setattr(campaign, "run_child", lambda cmd: calls.append(cmd[2]) or 0)
    monkeypatch.setattr(campaign, "copy_results", lambda run: None)
    assert campaign.main([str(path)]) == 0
    assert calls == ["experiments.restaurant"] * 3 and settled == [1, 1]
    assert "waited 10 s for the load average (now 1.00)" in capsys.readouterr().out
    loaded = campaign.load_campaign(path)
    assert [r.wall_clock for r in loaded] == [True, False, True]
    assert [r.time_budget for r in loaded] == [True, False, True]


def test_unknown_top_level_keys_and_results_under_a_file(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"runs": [_run()], "run": []}))
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['run'\]"):
        campaign.load_campaign(path)
    (tmp_path / "afile").write_text("x")
    bad = _write(tmp_path, [_run(results=str(tmp_path / "afile" / "res"))])
    with pytest.raises(ValueError, match=r"runs\[0\]: 'results' .*afile is a file"):
        campaign.load_campaign(bad)


def _trained(run, cfg):
    """A work folder as a finished learning run leaves it, with `cfg` as its config.json."""
    run.work.mkdir(parents=True)
    (run.work / "config.json").write_text(cfg.to_json())
    (run.work / "curve.json").write_text(json.dumps({"stopped": "budget"}))
    (run.work / campaign.TRAINED).write_text("{}")


def test_an_entry_edited_after_training_is_refused_not_copied(tmp_path, monkeypatch, capsys):
    """A finished entry whose argv was edited later used to be reported finished and its old
    run copied into the results folder; the config its argv builds is now compared with the
    run's config.json first (only the learning run's iteration count may differ)."""
    monkeypatch.chdir(tmp_path)
    ev = [["--split", "val", "--out", "{results}/eval/v"]]
    path = _write(tmp_path, [_run(evaluate=ev)])
    (run,) = campaign.load_campaign(path)
    cfg = campaign.built_config(run)
    _trained(run, cfg.replace(seed=7))
    calls = []
    monkeypatch.setattr(campaign, "run_child", lambda cmd: calls.append(cmd) or 0)
    assert campaign.main([str(path)]) == 2
    err = capsys.readouterr().err
    assert "a: its argv builds a config that differs" in err and "['seed']" in err
    assert not run.results.exists() and not calls
    import dataclasses

    (run.work / "config.json").write_text(
        cfg.replace(train=dataclasses.replace(cfg.train, iterations=17)).to_json()
    )
    assert campaign.main([str(path)]) == 0
    assert (run.results / "curve.json").is_file() and calls[0][2] == "lab.evaluation"


def test_a_run_killed_before_its_first_checkpoint_starts_afresh(tmp_path, monkeypatch):
    """A learning child killed before its first checkpoint left a folder every rerun refused
    ('exists and is not empty'); the campaign, whose work folder it is, clears it first."""
    monkeypatch.chdir(tmp_path)
    path = _write(tmp_path, [_run()])
    (run,) = campaign.load_campaign(path)
    (run.work / "checkpoints").mkdir(parents=True)
    (run.work / "metrics.jsonl").write_text('{"iteration": 1}\n')
    seen = []

    def child(cmd):
        seen.append(sorted(p.name for p in run.work.iterdir()) if run.work.exists() else [])
        return 130

    monkeypatch.setattr(campaign, "run_child", child)
    assert campaign.state_of(run) == "new"
    assert campaign.main([str(path)]) == 130
    assert seen == [[]]


def test_one_campaign_per_campaign_file(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    path = _write(tmp_path, [_run()])
    monkeypatch.setattr(campaign, "run_child", lambda cmd: 0)
    # another process holds the lock: simulated by holding it from a child process
    import subprocess

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from mpcpearl_jax.training.runlock import RunLock; "
            f"RunLock({str(campaign.WORK / '.c.json.campaign')!r}); print('held', flush=True); "
            "time.sleep(30)",
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        assert campaign.main([str(path)]) == 2
        assert "another campaign is running it" in capsys.readouterr().err
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGHUP", "SIGKILL"])
def test_a_stopped_campaign_lets_its_run_save_and_leaves_no_orphan(tmp_path, signame):
    """SIGTERM or SIGHUP to the campaign (`timeout`, a scheduler) used to leave the training
    child running as an orphan (and the rerun failed on its run lock): the child now gets
    SIGINT, saves, and the campaign ends after it (128 + the signal). Killed outright, the
    campaign cannot forward anything: the kernel sends the child SIGINT (PR_SET_PDEATHSIG)."""
    import os
    import signal
    import subprocess
    import time

    if not sys.platform.startswith("linux"):
        pytest.skip("the parent-death signal is Linux's")
    saved, ready, child = _guarded_child(tmp_path)
    parent = (
        "import sys; from lab import campaign; "
        f"sys.exit(campaign.run_child([sys.executable, '-c', {child!r}]))"
    )
    root = Path(__file__).resolve().parents[1]
    p = subprocess.Popen([sys.executable, "-c", parent], cwd=root, start_new_session=True)
    deadline = time.monotonic() + 60
    while not ready.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert ready.exists(), "the child did not start"
    sig = getattr(signal, signame)
    os.kill(p.pid, sig)
    rc = p.wait(timeout=30)
    if signame != "SIGKILL":
        assert rc == 128 + sig
    deadline = time.monotonic() + 30
    while not saved.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert saved.read_text() == "state"


def test_a_results_folder_holding_another_run_is_refused(tmp_path, monkeypatch, capsys):
    """An entry whose results folder already holds another run's records (and not its finished
    record) would have had them overwritten by its copy; it is refused before training."""
    monkeypatch.chdir(tmp_path)
    path = _write(tmp_path, [_run()])
    (run,) = campaign.load_campaign(path)
    run.results.mkdir(parents=True)
    (run.results / "config.json").write_text("{}")
    (run.results / "policy.msgpack").write_bytes(b"other")
    calls = []
    monkeypatch.setattr(campaign, "run_child", lambda cmd: calls.append(cmd) or 0)
    assert campaign.main([str(path)]) == 2
    assert "holds another run's records" in capsys.readouterr().err and not calls
    (run.results / campaign.TRAINED).write_text(json.dumps({"name": "a"}))  # a copy of its own
    assert campaign.main([str(path)]) == 0 and calls


RUN = Path(__file__).resolve().parents[1] / "results" / "restaurant" / "mpc-pearl-eps0.2"


def _without_wall(path: Path) -> dict:
    record = json.loads(path.read_text())
    record.pop("wall_s")
    return record


def test_an_evaluation_process_writes_the_record_the_command_writes(tmp_path, capsys):
    """A campaign's evaluation runs `mpcpearl_jax.evaluate` in its own process with keyword
    arguments (`lab.evaluation`, one JSON object), not the evaluation command's argv: its
    results.json is the one the command writes for the same flags."""
    from lab import evaluation
    from mpcpearl_jax.cli.evaluate import main as evaluate_command

    flags = ["--split", "val", "--tasks", "0-1", "--figures", "none", "--out"]
    ev = campaign.CampaignEvaluation.of(RUN, (*flags, str(tmp_path / "lab")))
    assert ev.arguments == {
        "run": str(RUN),
        "split": "val",
        "tasks": "0-1",
        "figures": "none",
        "out": str(tmp_path / "lab"),
    }
    assert evaluation.main([ev.command[-1]]) == 0
    out = capsys.readouterr().out
    assert f"wrote {tmp_path / 'lab' / 'results.json'}" in out and "val (task seed" in out
    assert evaluate_command([str(RUN), *flags, str(tmp_path / "cli")]) == 0
    cli = _without_wall(tmp_path / "cli" / "results.json")
    assert _without_wall(ev.record) == cli


def test_evaluation_keywords_hold_a_shield_and_errors_name_the_flags(tmp_path, capsys):
    from lab import evaluation
    from mpcpearl_jax.mpc.shield import ShieldConfig

    kw = evaluation.keywords(Path("res/a"), ["--shield", "--shield-margin", "0.3", "--out", "o"])
    assert kw["shield"] == {"margin": 0.3}
    run, decoded = evaluation.decode(json.dumps(kw))
    assert run == "res/a" and decoded["shield"] == ShieldConfig(margin=0.3)
    assert evaluation.keywords(Path("r"), ["--shield", "--out", "o"])["shield"] == {}
    steers = (-1.0, 0.0, 1.0)
    kw = {"run": "r", "shield": {"steers": list(steers)}}
    assert evaluation.decode(json.dumps(kw))[1]["shield"] == ShieldConfig(steers=steers)
    with pytest.raises(ValueError, match="need --shield"):
        evaluation.keywords(Path("res/a"), ["--shield-lookahead", "3", "--out", "o"])
    # a bad argument met when the evaluation starts: one line naming the command's flag
    bad = {"controller": "gp-mpc", "tasks": "0-99", "out": str(tmp_path / "o")}
    assert evaluation.main([json.dumps(bad)]) == 2
    assert capsys.readouterr().err.startswith("error: --tasks: task(s) [24, 25, 26]")
    assert evaluation.main(['["not", "an object"]']) == 2
    assert "expected a JSON object" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_the_dry_run_prints_each_process_as_a_shell_line(tmp_path, monkeypatch, capsys):
    import shlex

    monkeypatch.chdir(tmp_path)
    ev = [["--split", "val", "--task-seeds", "1-8", "--out", "{results}/eval/v"]]
    assert campaign.main([str(_write(tmp_path, [_run(evaluate=ev)])), "--dry-run"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("[campaign] $")]
    argv = shlex.split(lines[1].removeprefix("[campaign] $ "))
    assert argv[:2] == ["-m", "lab.evaluation"]
    assert json.loads(argv[2]) == {
        "run": "res/a",
        "split": "val",
        "task_seeds": "1-8",
        "out": "res/a/eval/v",
    }
