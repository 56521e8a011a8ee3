"""Bad or edge inputs that used to break a command (a traceback, memory exhausted, an option
silently ignored), each now one line naming the option, field or file (exit 2), or honoured:
ranges bounded before they are expanded (Q2, Q3), unwritable export targets (Q4, Q5), an unknown
family for the GP-MPC command (Q6), an evaluation seed out of range (Q7), a custom family's run
evaluated with --env MODULE:NAME (Q8), --online with --episodes (Q9) and an export sidecar whose
t_update exceeds the episode (Q11). Q1 and Q10 (stop signals) are in test_stop_signals.py."""

from __future__ import annotations

import builtins
import json
import shutil
from pathlib import Path

import pytest
from faults_helpers import _make_unwritable

import mpcpearl_jax.cli.evaluate as evaluate
import mpcpearl_jax.evaluation.plan as evaluation_plan
from experiments import export, gp_mpc

ROOT = Path(__file__).resolve().parents[1]
MAIN_RUN = ROOT / "results/restaurant/main-default"
HEADLINE = ROOT / "results/restaurant/mpc-pearl-eps0.2"


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    return err


@pytest.fixture
def bounded_range(monkeypatch):
    """`range` in experiments.evaluate and the library behind it (mpcpearl_jax.evaluation.plan)
    refuses to be expanded past a million values (a range expanded before its bound is checked
    fails here instead of filling the memory)."""

    def guarded(*args):
        r = builtins.range(*args)
        assert len(r) <= 10**6, f"a range of {len(r)} values was expanded"
        return r

    monkeypatch.setattr(evaluate, "range", guarded, raising=False)
    monkeypatch.setattr(evaluation_plan, "range", guarded, raising=False)


def test_q2_a_huge_tasks_range_is_refused_before_it_is_expanded(bounded_range, capsys, tmp_path):
    with pytest.raises(evaluate.UsageError, match=r"\[24, 25, 26\] and 2999999974 more out of"):
        evaluate.parse_indices("0-3000000000", 24, "--tasks")
    out = str(tmp_path / "e")
    assert evaluate.main([str(MAIN_RUN), "--tasks", "0-3000000000", "--out", out]) == 2
    assert "--tasks: task(s) [24, 25, 26] and 2999999974 more out of range" in _one_line(capsys)
    assert evaluate.parse_indices("3,0-2,1-1", 24, "--tasks") == [0, 1, 2, 3]


def test_q3_a_huge_task_seeds_range_is_refused_before_it_is_expanded(
    bounded_range, capsys, tmp_path
):
    argv = [str(MAIN_RUN), "--task-seeds", "0-3000000000", "--out", str(tmp_path / "e")]
    assert evaluate.main(argv) == 2
    err = _one_line(capsys)
    assert f"3000000001 task sets; at most {evaluate.MAX_TASK_SEEDS}" in err
    # overlapping spans count once
    assert evaluation_plan.parse_ranges("1-8,3-5,8", "task_seeds", 8) == set(range(1, 9))


def test_q4_an_export_into_a_read_only_folder_is_one_line(tmp_path, capsys):
    folder = tmp_path / "ro"
    folder.mkdir()
    undo = _make_unwritable(folder)
    try:
        assert export.main([str(HEADLINE), "--out", str(folder / "p.export")]) == 2
    finally:
        undo()
    err = _one_line(capsys)
    assert f"{folder}: cannot write the export there" in err and "--out" in err
    assert list(folder.iterdir()) == []


def test_q5_an_export_under_a_file_is_one_line(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert export.main([str(HEADLINE), "--out", str(afile / "p.export")]) == 2
    err = _one_line(capsys)
    assert f"{afile}: cannot write the export there (a file is where a folder should be)" in err
    assert afile.read_text() == "x"


def test_q6_gp_mpc_with_an_unknown_family_is_one_line(tmp_path, capsys):
    assert gp_mpc.main(["--env", "nosuch", "--out", str(tmp_path / "g")]) == 2
    err = _one_line(capsys)
    assert err.startswith("error: --env nosuch: no such task family")
    assert not (tmp_path / "g").exists()


def test_q6_gp_mpc_with_an_unwritable_out_stops_before_the_rollout(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert gp_mpc.main(["--max-tasks", "1", "--out", str(afile / "g")]) == 2
    assert f"--out {afile / 'g'}: not writable" in _one_line(capsys)


def test_q7_an_eval_seed_out_of_range_is_one_line(tmp_path, capsys):
    argv = [str(MAIN_RUN), "--eval-seed", "99999999999999999999", "--out", str(tmp_path / "e")]
    assert evaluate.main(argv) == 2
    assert "--eval-seed 99999999999999999999: not a PRNG seed" in _one_line(capsys)
    assert not (tmp_path / "e").exists()


def test_q9_online_with_episodes_is_one_line_not_ignored(tmp_path, capsys):
    argv = [str(MAIN_RUN), "--online", "--episodes", "2", "--out", str(tmp_path / "e")]
    assert evaluate.main(argv) == 2
    err = _one_line(capsys)
    assert "--episodes" in err and "--online" in err


def _corridor_run(tmp_path: Path) -> Path:
    """A corridor run's folder with its config.json only (no policy)."""
    import examples.corridor  # noqa: F401  (registers the family)
    from mpcpearl_jax.config import resolve
    from mpcpearl_jax.runfolder import save_config

    run = tmp_path / "corridor-run"
    run.mkdir()
    save_config(run, resolve("smoke", "corridor"))
    return run


def test_q8_a_custom_family_run_takes_env_module_name(tmp_path, capsys):
    """--env MODULE:NAME names the family the run was trained on: accepted (here the missing
    policy is the next error); another family is refused naming both."""
    run = _corridor_run(tmp_path)
    out = str(tmp_path / "e")
    assert evaluate.main([str(run), "--env", "examples.corridor:corridor", "--out", out]) == 2
    err = _one_line(capsys)
    assert "policy.msgpack" in err and "trained on" not in err
    assert evaluate.main([str(run), "--env", "restaurant", "--out", out]) == 2
    assert f"--env restaurant: the run {run} was trained on corridor" in _one_line(capsys)
    assert evaluate.main([str(run), "--env", "examples.corridor:nosuch", "--out", out]) == 2
    assert "registered no family 'nosuch'" in _one_line(capsys)


def test_q11_a_sidecar_t_update_beyond_the_episode_is_refused(tmp_path):
    from mpcpearl_jax.deploy.exported import ExportError, load_exported, sidecar_path

    out = tmp_path / "policy.export"  # copied away from its run: no config.json beside it
    shutil.copy(HEADLINE / "policy.export", out)
    meta = json.loads((HEADLINE / "policy.export.json").read_text())
    horizon = meta["env_config"]["horizon"]
    sidecar_path(out).write_text(json.dumps({**meta, "t_update": 1000}))
    with pytest.raises(ExportError, match=rf"t_update must be at most .*\({horizon} steps\)"):
        load_exported(out)
    sidecar_path(out).write_text(json.dumps({**meta, "t_update": horizon}))
    assert load_exported(out).t_update == horizon


# ---------------------------------------------------------------- JAX_PLATFORMS this machine lacks


def _platform_line(module: str, args: list[str], platform: str, tmp_path: Path) -> str:
    import subprocess
    import sys

    from faults_helpers import _env

    env = {**_env(), "JAX_PLATFORMS": platform}
    proc = subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    err = proc.stderr.strip()
    assert proc.returncode == 2 and "\n" not in err, (module, proc.returncode, err)
    assert err.startswith(f"error: JAX_PLATFORMS={platform}: not available on this machine"), err
    assert "unset JAX_PLATFORMS" in err
    return err


PLATFORM_COMMANDS = {
    "experiments.restaurant": ["--preset", "smoke"],
    "experiments.grbal": ["--preset", "smoke"],
    "experiments.gp_mpc": ["--max-tasks", "1"],
    "experiments.evaluate": [str(HEADLINE)],
    "experiments.export": [str(HEADLINE)],
    "benchmarks.env_throughput": ["--tiny"],
    "benchmarks.mpc_latency": ["--tasks", "1"],
    "lab.diagnostics.shield": ["--tiny"],
}


@pytest.mark.skipif(
    __import__("jax").default_backend() != "cpu", reason="the machine has an accelerator"
)
@pytest.mark.parametrize(
    "module",
    [
        m
        if m in ("experiments.restaurant", "benchmarks.env_throughput")
        else pytest.param(m, marks=pytest.mark.slow)
        for m in PLATFORM_COMMANDS
    ],
)
def test_a_platform_this_machine_lacks_is_one_line(module, tmp_path):
    """JAX_PLATFORMS=cuda (or gpu, or a misspelt name) on a CPU machine: a 58-68-line traceback
    of JAX's backend start; now one line saying so and how to fix it, before anything is
    written."""
    out = tmp_path / "out"
    args = [*PLATFORM_COMMANDS[module], "--out", str(out)]
    _platform_line(module, args, "cuda", tmp_path)
    if module == "experiments.gp_mpc":
        assert "knows: cpu" in _platform_line(module, args, "bogus", tmp_path)
        _platform_line(module, args, "gpu", tmp_path)
    assert not out.exists() or not any(out.iterdir())  # nothing written


def test_the_platform_check_starts_nothing_for_the_cpu(monkeypatch):
    """The check runs where the commands start: unless a platform other than the CPU is asked
    for, it must not start JAX's backend (thread settings come first)."""
    import jax

    from mpcpearl_jax.cli import platform

    def started():
        raise AssertionError("the backend was started")

    monkeypatch.setattr(jax, "devices", started)
    for asked in ("", "cpu", " cpu "):
        monkeypatch.setattr(platform, "requested_platforms", lambda asked=asked: asked)
        platform.check_platform()
    monkeypatch.setattr(platform, "requested_platforms", lambda: "cuda")
    with pytest.raises(platform.PlatformError, match="JAX_PLATFORMS=cuda: not available"):
        platform.check_platform()


# ---------------------------------------------------------------- --env MODULE:NAME that fails

BAD_MODULES = {
    "raises": ("raise RuntimeError('no GPU found for my task')\n", "failed: RuntimeError: no GPU"),
    "syntax": ("def broken(:\n    pass\n", "has a syntax error (invalid syntax, "),
    "exits": ("import sys\nsys.exit(0)\n", "exited (sys.exit(0))"),
}


@pytest.mark.parametrize("kind", sorted(BAD_MODULES))
def test_an_env_module_that_fails_to_import_is_one_line(kind, tmp_path, monkeypatch, capsys):
    """--env MODULE:NAME whose module raises on import or has a syntax error: a full traceback;
    one that calls sys.exit(0): --print-config printed nothing and exited 0."""
    from mpcpearl_jax.cli.train import main

    name = f"edge_family_{kind}"
    (tmp_path / f"{name}.py").write_text(BAD_MODULES[kind][0])
    monkeypatch.syspath_prepend(str(tmp_path))
    spec = f"{name}:corridor"
    expected = f"error: --env {spec}: "
    assert main("restaurant", ["--env", spec, "--print-config"]) == 2
    out, err = capsys.readouterr()
    assert not out and err.startswith(expected) and BAD_MODULES[kind][1] in err, err
    assert "\n" not in err.strip() and name in err
    assert gp_mpc.main(["--env", spec, "--out", str(tmp_path / "g")]) == 2
    line = _one_line(capsys)
    assert line.startswith(expected) and BAD_MODULES[kind][1] in line


# ---------------------------------------------------------------- the family: --env, not --set


def test_the_family_is_chosen_by_env_not_by_set(capsys):
    """`--set env.name=...`, listed as settable by --help-config, failed with "make_env() got
    multiple values for argument 'name'"; it is one line pointing at --env, and --help-config
    (test_learning_harness) no longer lists it. The library says the same."""
    from mpcpearl_jax.cli.train import main
    from mpcpearl_jax.config import ConfigError, ExperimentConfig
    from mpcpearl_jax.envs import make_env

    for item, owner in (
        ("env.name=sidewalk", "NavConfig.name"),
        ("env=sidewalk", "ExperimentConfig.env"),
    ):
        assert main("restaurant", ["--set", item, "--print-config"]) == 2
        out, err = capsys.readouterr()
        assert not out and err.strip() == (
            f"error: --set {item}: {owner} is the task family: choose it with --env, not --set"
        )
    with pytest.raises(ConfigError, match="'name' is the task family"):
        ExperimentConfig(env_overrides={"name": "sidewalk"})
    with pytest.raises(ConfigError, match="NavConfig.name is the task family"):
        make_env("restaurant", name="sidewalk")
