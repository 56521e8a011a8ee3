"""Every benchmark script runs at its tiny size and writes its JSON record (so none can rot).

Numbers from these runs mean nothing: the sizes are chosen only to exercise the code.
"""

from __future__ import annotations

import importlib
import json
import math
import os
from pathlib import Path

import pytest

SCRIPTS = [
    "env_throughput",
    "collection",
    "pearl_step",
    "policy_latency",
    "memory",
    "iteration",
    "pipeline",
    "grbal_planner",
    "learner_sizes",
    "mpc_bridge",
]


@pytest.fixture
def clean_environ():
    """Restore the environment variables the scripts set, and compile with few optimisations."""
    import jax

    saved = dict(os.environ)
    os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"  # for child processes
    jax.config.update("jax_disable_most_optimizations", True)
    yield
    jax.config.update("jax_disable_most_optimizations", False)
    os.environ.clear()
    os.environ.update(saved)


# the cheap ones in the fast set; the others (12-32 s each) with the slow tests
FAST_SCRIPTS = ("env_throughput", "policy_latency")


@pytest.mark.parametrize(
    "name",
    [n if n in FAST_SCRIPTS else pytest.param(n, marks=pytest.mark.slow) for n in SCRIPTS],
)
def test_script_runs_tiny(name: str, tmp_path: Path, clean_environ) -> None:
    module = importlib.import_module(f"benchmarks.{name}")
    module.main(["--tiny", "--out", str(tmp_path)])
    record = json.loads((tmp_path / f"{name}.json").read_text())
    assert record["benchmark"] == name
    assert record["config"]["size"] == "tiny"
    assert {"platform", "cpu_count", "jax"} <= set(record["machine"])
    assert record["results"]


def test_torch_baseline_step_changes_parameters() -> None:
    torch = pytest.importorskip("torch")
    from benchmarks.torch_pearl import TorchPearl, TorchPearlSizes, random_batch

    sizes = TorchPearlSizes(hidden=(16, 16), encoder_hidden=(16, 16), latent_dim=3)
    model = TorchPearl(5, 2, sizes)
    before = [p.detach().clone() for p in model.policy.parameters()]
    enc_before = [p.detach().clone() for p in model.encoder.parameters()]
    losses = model.step(*random_batch(2, 8, 4, 5, 2))
    assert all(math.isfinite(v) for v in losses.values())
    assert any(
        not torch.equal(a, b) for a, b in zip(before, model.policy.parameters(), strict=True)
    )
    assert any(
        not torch.equal(a, b) for a, b in zip(enc_before, model.encoder.parameters(), strict=True)
    )


def test_all_lists_every_script() -> None:
    from benchmarks import all as bench_all

    root = Path(bench_all.__file__).parent
    assert set(SCRIPTS) <= set(bench_all.SCRIPTS)
    for name in SCRIPTS:
        assert (root / f"{name}.py").is_file()


@pytest.mark.slow  # a diagnostic outside the README's commands (~30-50 s)
def test_imitation_diagnostic_runs_tiny(tmp_path: Path, clean_environ) -> None:
    """`lab.diagnostics.imitation` (a diagnostic, not part of the speed suite) on the
    committed
    headline run: errors on the MPC's states, the BC curve and its closed-loop metrics."""
    from lab.diagnostics import imitation

    res = imitation.main(["--tiny", "--out", str(tmp_path)])
    record = json.loads((tmp_path / "imitation-tiny.json").read_text())
    assert record["config"]["size"] == "tiny" and record["results"]["bc_selected_steps"] in (5, 10)
    assert [row["steps"] for row in res["bc_curve"]] == [5, 10]
    errors = [res["label_variance"], res["train_label_variance"]]
    errors += [e for split in res["policy_error"].values() for e in split.values()]
    errors += [row["val_error"] for row in res["bc_curve"]]
    assert all(0.0 <= e <= 8.0 for e in errors)  # two normalized dims: |a - b|^2 <= 8
    assert 0 < res["samples"]["val"] <= 2 * 80 and 0 < res["samples"]["train"] <= 2 * 80
    seeds = res["bc_closed_loop"]["per_task_seed"]
    assert list(seeds) == [1] and 0.0 <= seeds[1]["SR"] <= seeds[1]["CFR"] <= 1.0


@pytest.mark.slow  # a diagnostic outside the README's commands (~30-50 s)
def test_dagger_diagnostic_runs_tiny(tmp_path: Path, clean_environ) -> None:
    """`lab.diagnostics.dagger` (a diagnostic) with the egocentric, sorted observation:
    labelled
    states accumulate over the rounds (round 0 is the MPC alone, every later round executes the
    clone on most steps), and the record names the observation options it used (`--presence`
    adds the presence entries to the MLP's input) and the clone's parameter count."""
    from lab.diagnostics import dagger
    from mpcpearl_jax.envs import make_env, make_tasks

    argv = ["--tiny", "--relative", "--sorted", "--presence", "--out", str(tmp_path)]
    res = dagger.main(argv)
    record = json.loads((tmp_path / "dagger-relative-sorted-presence-tiny.json").read_text())
    assert record["config"]["size"] == "tiny" and record["config"]["sorted"]
    assert record["config"]["presence"] and dagger.arm_of(record["config"]) == "mlp + presence"
    obs = res["observation"]
    assert obs["observe_relative"] and obs["observe_sorted"] and obs["observe_presence"]
    env = make_env("restaurant", **obs)
    o = env.obs_dim(make_tasks("restaurant", "val", 1, config=env.config))
    h = 128  # the default hidden sizes 128, 128, 128, tanh output of 2
    assert res["parameters"] == (o + 1) * h + 2 * (h + 1) * h + (h + 1) * 2
    curve = res["curve"]
    assert [row["round"] for row in curve] == [0, 1] and [row["beta"] for row in curve] == [1, 0.5]
    assert 0 < curve[0]["samples"] < curve[1]["samples"] <= 2 * 2 * 80  # two tasks, two rounds
    assert all(0.0 <= row["fit_error"] <= 8.0 for row in curve)
    final = res["final"]["mean"]
    assert list(res["final"]["per_task_seed"]) == [1] and 0.0 <= final["SR"] <= final["CFR"] <= 1


@pytest.mark.slow  # a diagnostic outside the README's commands (~60-110 s)
def test_dagger_diagnostic_runs_tiny_with_the_crowd_encoder(tmp_path: Path, clean_environ) -> None:
    """The clone with the crowd encoder and the forecast, twice the tasks per round, seed 1:
    the observation gains the presence and forecast entries, the record names its arm."""
    from lab.diagnostics import dagger

    argv = ["--tiny", "--relative", "--sorted", "--encoder", "attention", "--forecast", "2"]
    res = dagger.main([*argv, "--labels", "2", "--seed", "1", "--out", str(tmp_path)])
    name = "dagger-relative-sorted-attention-forecast2x1-labels2-tiny-seed1.json"
    record = json.loads((tmp_path / name).read_text())
    assert record["config"]["encoder"] == "attention" and record["config"]["labels"] == 2
    assert res["observation"]["observe_presence"] and res["observation"]["observe_forecast"] == 2
    assert 0 < res["curve"][0]["samples"] <= 2 * 2 * 80  # two layouts x two crowds, one round
    assert 0.0 <= res["final"]["mean"]["SR"] <= 1.0


def test_dagger_report_groups_seeds_by_arm(tmp_path: Path) -> None:
    """`--report`: seeds of one arm pooled, the MLP arm of the same inputs as the baseline of
    P(improvement), records of the tiny size left out, a folder without records one line."""
    from lab.diagnostics import dagger

    def record(name, encoder, seed, sr, size="default", forecast=0):
        config = {"size": size, "encoder": encoder, "forecast": forecast, "stride": 2}
        config.update(labels=1, seed=seed)
        results = {"curve": [{"samples": 100 + seed}], "final": {"mean": {"SR": sr}}}
        (tmp_path / f"{name}.json").write_text(json.dumps({"config": config, "results": results}))

    for seed, (a, b) in enumerate([(0.6, 0.2), (0.5, 0.25), (0.7, 0.1)]):
        record(f"dagger-att-s{seed}", "attention", seed, a, forecast=5)
        record(f"dagger-mlp-s{seed}", "mlp", seed, b)
    record("dagger-tiny", "mlp", 9, 1.0, size="tiny")
    rows = {r["arm"]: r for r in dagger.report(tmp_path)["arms"]}
    att, mlp = rows["attention + forecast 5x2"], rows["mlp"]
    assert att["seeds"] == [0, 1, 2] and att["val_SR"] == [0.6, 0.5, 0.7]
    assert att["worst"] == 0.5 and abs(att["mean"] - 0.6) < 1e-9
    assert att["vs"] == "mlp" and att["improvement"]["value"] == 1.0
    assert mlp["improvement"] is None and 9 not in mlp["seeds"]
    assert "| attention + forecast 5x2 | 3 |" in (tmp_path / "README.md").read_text()
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no DAgger record"):
        dagger.report(empty)


@pytest.mark.slow  # a diagnostic outside the README's commands (~20 s)
def test_shield_diagnostic_runs_tiny(tmp_path: Path, clean_environ) -> None:
    """`lab.diagnostics.shield` (a diagnostic) on the committed headline run: one row per
    (controller, shield setting), the unshielded rows with no replaced step, rates in range."""
    from lab.diagnostics import shield

    run = Path(__file__).resolve().parents[1] / "results" / "restaurant" / "mpc-pearl-eps0.2"
    res = shield.main(["--tiny", "--runs", str(run), "--out", str(tmp_path)])
    record = json.loads((tmp_path / "shield-tiny.json").read_text())
    assert record["config"]["size"] == "tiny"
    assert record["config"]["runs"] == ["results/restaurant/mpc-pearl-eps0.2"]
    rows = res["rows"]
    assert [(r["controller"], r["shield"] is None) for r in rows] == [
        ("goal-seeking", True),
        ("goal-seeking", False),
        ("mpc-pearl-eps0.2", True),
        ("mpc-pearl-eps0.2", False),
    ]
    for r in rows:
        p = r["pooled"]
        free = p["collision_free"]["mean"]
        assert 0.0 <= p["success"]["mean"] <= free and p["timeout"]["mean"] <= free
        assert 0.0 <= p["shield_rate"]["mean"] <= 1.0
        if r["shield"] is None:
            assert p["shield_rate"]["mean"] == 0.0
    # the goal-seeking control alone drives into the first table
    assert rows[0]["pooled"]["collision_free"]["mean"] == 0.0


def test_crowd_cause_interventions_change_only_what_they_name() -> None:
    """`lab.diagnostics.crowd_cause`'s observation interventions: the clock reads max(t -
    K, 0) and
    nothing else moves; blind hides every person (as the env shows an absent one) and keeps the
    pose, static and goal parts; no intervention is the env's own observation."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from lab.diagnostics.crowd_cause import intervened_env
    from mpcpearl_jax import make_env, make_tasks
    from mpcpearl_jax.envs.types import EnvState

    env = make_env("restaurant", observe_time=True, observe_velocity=True)
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test"))
    horizon = env.config.horizon
    for t in (0, 5, 30):
        state = EnvState(pose=task.start, t=jnp.asarray(t, jnp.int32))
        own = np.asarray(env.observe(state, task))
        np.testing.assert_array_equal(intervened_env(env.config).observe(state, task), own)
        lag = np.asarray(intervened_env(env.config, clock_lag=12).observe(state, task))
        np.testing.assert_array_equal(lag[:-1], own[:-1])
        assert lag[-1] == pytest.approx(2 * max(t - 12, 0) / horizon - 1)
        blind = np.asarray(intervened_env(env.config, blind=True).observe(state, task))
        gone = task.replace(human_mask=jnp.zeros_like(task.human_mask))
        np.testing.assert_array_equal(blind, env.observe(state, gone))
        np.testing.assert_array_equal(blind[:3], own[:3])
        assert not np.array_equal(blind, own)  # people are present in this task


@pytest.mark.slow
def test_crowd_cause_runs_tiny(tmp_path: Path, clean_environ) -> None:
    """`lab.diagnostics.crowd_cause` on the committed headline run: every condition once
    per delay,
    the as-trained rows equal to experiments.evaluate's numbers on the same tasks."""
    from lab.diagnostics import crowd_cause

    run = Path(__file__).resolve().parents[1] / "results" / "restaurant" / "mpc-pearl-eps0.2"
    res = crowd_cause.main(["--tiny", "--runs", str(run), "--out", str(tmp_path), "--delay", "6"])
    rows = res["rows"]
    assert [(r["condition"], r["delay"]) for r in rows] == [
        ("as trained", 0),
        ("blind", 0),
        ("zero-shot", 0),
        ("as trained", 6),
        ("clock follows the crowd", 6),
        ("blind", 6),
        ("zero-shot", 6),
    ]
    for r in rows:
        p = r["pooled"]
        assert 0.0 <= p["success"]["mean"] <= p["collision_free"]["mean"] <= 1.0
        assert (r["path_shift_m"] is None) == (r["delay"] == 0)
    record = json.loads((tmp_path / "crowd_cause-tiny-delay6.json").read_text())
    assert record["config"]["delay"] == 6


@pytest.mark.slow  # (~12 s) pearl_step's tiny run is in the fast set
def test_pearl_step_takes_the_seed_counts_it_is_given(tmp_path: Path, clean_environ) -> None:
    from benchmarks import pearl_step

    pearl_step.main(["--tiny", "--seeds", "3", "--out", str(tmp_path)])
    record = json.loads((tmp_path / "pearl_step.json").read_text())
    assert [r["seeds"] for r in record["results"]["seeds"]] == [3]
    assert record["config"]["seeds"] == [3]
    with pytest.raises(SystemExit, match="--seeds"):
        pearl_step.main(["--tiny", "--seeds", "0", "--out", str(tmp_path)])


def _metrics(folder: Path, steps: list[float], extra: str = "") -> None:
    """A run folder's metrics.jsonl with one row per iteration taking `steps[i]` seconds
    (train_s is their running sum; wall_s adds 5 s of evaluation per row), collect_s and
    update_s of 60 % and 40 % of each step, an evaluation row without collect_s first, and
    `extra` appended (e.g. a line cut off by a stop)."""
    folder.mkdir(parents=True)
    rows, train, wall = [{"iteration": 0, "test_SR": 0.0}], 0.0, 0.0
    for i, s in enumerate(steps, 1):
        train, wall = train + s, wall + s + 5.0
        rows.append(
            {
                "iteration": i,
                "collect_s": 0.6 * s,
                "update_s": 0.4 * s,
                "train_s": train,
                "wall_s": wall,
            }
        )
    text = "".join(json.dumps(r) + "\n" for r in rows)
    (folder / "metrics.jsonl").write_text(text + extra)


def test_gpu_summary_medians_and_targets(tmp_path: Path) -> None:
    """`benchmarks.gpu_summary` on a fabricated session: medians over iterations 3 to the last
    (the last alone for a run of two iterations, none for one), the faster recipe run, the
    default's GPU speed-up and each target's verdict; the README's GPU lines from its record,
    and "not yet measured" without one; a run of other seeds than the target's does not count."""
    from benchmarks import gpu_summary
    from lab.tables.statistics import Records
    from lab.tables.summary import render_gpu_session

    (tmp_path / "results").mkdir()
    out = tmp_path / "benchmarks" / "results" / "gpu-test"
    _metrics(out / "recipe", [10.0, 2.0, 1.0, 1.2, 1.0], extra='{"iteration": 6, "coll')
    _metrics(out / "recipe-pipeline", [20.0, 3.0, 0.5, 0.5])  # 2 seeds: not the target's
    (out / "recipe-pipeline" / "config.json").write_text('{"seeds": 2, "train": {"pipeline": 1}}')
    _metrics(out / "default-gpu", [30.0, 1.0, 0.5, 0.7, 0.6])
    _metrics(out / "default-cpu", [40.0, 3.0, 1.5, 1.5, 1.8])
    _metrics(out / "paper", [50.0, 2.0])
    (out / "machine.txt").write_text("name, memory.total [MiB]\nNVIDIA H200, 143771 MiB\n")
    summary = gpu_summary.main([str(out)])
    assert json.loads((out / "summary.json").read_text())["targets"] == summary["targets"]
    runs = summary["runs"]
    assert runs["recipe"]["iterations"] == 5 and runs["recipe"]["timed"] == 3
    assert runs["recipe"]["median_iteration_s"] == pytest.approx(1.0)
    assert runs["recipe"]["median_collect_s"] == pytest.approx(0.6)
    assert runs["recipe"]["median_update_s"] == pytest.approx(0.4)
    assert runs["recipe"]["median_wall_step_s"] == pytest.approx(6.0)
    assert runs["recipe"]["first_iteration_s"] == pytest.approx(10.0)
    assert runs["recipe-pipeline"]["median_iteration_s"] == pytest.approx(0.5)
    assert runs["recipe-pipeline"]["seeds"] == 2 and "seeds" not in runs["recipe"]
    assert runs["paper"]["timed_from"] == 2 and runs["paper"]["median_iteration_s"] == 2.0
    t = {x["name"]: x for x in summary["targets"]}
    assert (t["recipe_s"]["figure"], t["recipe_s"]["run"], t["recipe_s"]["met"]) == (
        pytest.approx(1.0),
        "recipe",
        True,
    )
    assert t["default_speedup"]["figure"] == pytest.approx(2.5) and t["default_speedup"]["met"]
    assert t["paper_s"]["figure"] == pytest.approx(2.0) and t["paper_s"]["met"] is False
    assert summary["machine"]["gpu"] == "NVIDIA H200"
    text = "\n".join(gpu_summary.lines(summary))
    assert "target paper_s" in text and "NOT met" in text

    one = gpu_summary.run_summary(gpu_summary.read_rows(out / "paper" / "metrics.jsonl")[:1])
    assert one["timed"] == 0 and one["median_iteration_s"] is None
    assert gpu_summary.targets({})[0]["figure"] is None

    rec = Records(tmp_path / "results")
    lines = "\n".join(render_gpu_session(rec))
    assert "Training on NVIDIA H200" in lines and "`benchmarks/results/gpu-test/`" in lines
    assert "| 1.00 s (without `train.pipeline`) | <= 1.5 s: met |" in lines
    assert "| 2.50x (GPU 0.600 s, CPU 1.50 s) | >= 2x: met |" in lines
    assert "| 2.00 s | <= 1.5 s: not met |" in lines
    assert not rec.missing
    (tmp_path / "elsewhere" / "results").mkdir(parents=True)
    rec = Records(tmp_path / "elsewhere" / "results")
    lines = "\n".join(render_gpu_session(rec))
    assert lines.count("not yet measured") == 3 and not rec.missing


def test_gpu_session_script_parses() -> None:
    """benchmarks/gpu_session.sh is valid bash and calls only what exists."""
    import subprocess

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu_session.sh"
    subprocess.run(["bash", "-n", str(script)], check=True)
    text = script.read_text()
    for module in ("experiments.restaurant", "benchmarks.pipeline", "benchmarks.collection",
                   "benchmarks.gpu_summary"):  # fmt: skip
        assert f"-m {module}" in text
        assert importlib.util.find_spec(module) is not None


# ------------------------------------------------------------ where records go, checked up front


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    return err


def test_records_go_to_the_scratch_folder_unless_record_or_out(tmp_path: Path) -> None:
    """Without --record or --out a benchmark writes into the git-ignored scratch folder (it
    wrote over the committed record the README quotes); --record names the committed one."""
    from benchmarks import harness

    p = harness.common_parser("x")
    assert Path(p.parse_args([]).out) == harness.SCRATCH
    assert Path(p.parse_args(["--record"]).out) == harness.RECORDS
    assert p.parse_args(["--out", str(tmp_path / "o")]).out == str(tmp_path / "o")
    assert harness.RECORDS == Path(__file__).resolve().parents[1] / "benchmarks" / "results"
    assert "benchmarks/results/scratch/" in (harness.RECORDS.parents[1] / ".gitignore").read_text()


@pytest.mark.parametrize(
    "argv",
    [
        ["--tiny", "--record"],
        ["--tiny", "--out", "benchmarks/results"],
        ["--tiny", "--out", "benchmarks/results/gpu-h100"],
    ],
)
def test_a_tiny_run_never_replaces_a_measured_record(argv, capsys, monkeypatch) -> None:
    """`benchmarks.env_throughput --tiny` wrote over benchmarks/results/env_throughput.json and
    exited 0; `benchmarks.all --tiny` would have replaced every record."""
    from benchmarks import all as bench_all
    from benchmarks import env_throughput, harness

    monkeypatch.chdir(harness.RECORDS.parents[1])
    record = harness.RECORDS / "env_throughput.json"
    before = record.read_bytes()
    for main in (env_throughput.main, bench_all.main):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2
        assert "--tiny is a smoke run and never replaces a measured record" in _error_line(capsys)
    assert record.read_bytes() == before


def test_benchmark_flags_are_checked_before_it_runs(tmp_path: Path, capsys) -> None:
    """--threads beyond the cores (a ValueError traceback), --out on a file or on a folder that
    cannot be written (found only after the benchmark had run): one line, exit 2, at once."""
    from faults_helpers import _make_unwritable

    from benchmarks import env_throughput

    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    locked = tmp_path / "locked"
    locked.mkdir()
    cases = [
        (["--threads", "999"], "--threads 999: this process may use 1 to"),
        (["--threads", "0"], "--threads 0: this process may use 1 to"),
        (["--out", str(a_file)], f"--out {a_file}: not writable (a file is"),
        (["--out", str(locked / "sub")], f"--out {locked / 'sub'}: not writable"),
    ]
    undo = _make_unwritable(locked)
    try:
        for argv, expected in cases:
            with pytest.raises(SystemExit) as exit_:
                env_throughput.main(["--tiny", *argv])
            assert exit_.value.code == 2
            assert expected in _error_line(capsys)
    finally:
        undo()


def test_record_mpc_problems_checks_out_before_its_training(tmp_path: Path, capsys, monkeypatch):
    """`record_mpc_problems --out` under a regular file, or a folder: the training ran its 90
    seconds first and then ended in a traceback writing nothing. One line, exit 2, at once."""
    from benchmarks import record_mpc_problems

    def never(*a, **k):
        raise AssertionError("the training ran")

    monkeypatch.setattr(record_mpc_problems, "record", never)
    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    cases = [
        (a_file / "p.npz", f"--out {a_file / 'p.npz'}: not writable (a file is"),
        (tmp_path, f"--out {tmp_path}: a folder; give the file's name"),
        # a folder not there yet, named with a trailing slash: it became a file DIR.npz
        (f"{tmp_path / 'new'}/", f"--out {tmp_path / 'new'}/: a folder; give the file's name"),
    ]
    for out, expected in cases:
        with pytest.raises(SystemExit) as exit_:
            record_mpc_problems.main(["--out", str(out)])
        assert exit_.value.code == 2
        assert expected in _error_line(capsys)
    assert a_file.read_text() == "x"


def test_mpc_latency_refuses_zero_tasks_before_its_episodes(capsys, monkeypatch) -> None:
    """`mpc_latency --tasks 0` ended in an IndexError after 27 s of episodes."""
    from benchmarks import mpc_latency

    def never(*a, **k):
        raise AssertionError("the episodes ran")

    monkeypatch.setattr(mpc_latency, "closed_loop", never)
    for n in ("0", "-3", "25"):
        with pytest.raises(SystemExit) as exit_:
            mpc_latency.main(["--tasks", n])
        assert exit_.value.code == 2
        assert f"--tasks {n}: give 1 to 24" in _error_line(capsys)


def test_policy_latency_on_a_corrupt_run_is_one_line(tmp_path: Path, capsys, monkeypatch):
    """`policy_latency --run` on a run folder whose config is cut off: a CheckpointError
    traceback."""
    from benchmarks import policy_latency

    monkeypatch.setattr(policy_latency.harness, "configure_threads", lambda n: {"threads": n})
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{")
    with pytest.raises(SystemExit) as exit_:
        policy_latency.main(["--tiny", "--run", str(run), "--out", str(tmp_path / "o")])
    assert exit_.value.code == 2
    assert _error_line(capsys).startswith(f"error: --run {run}: ")
