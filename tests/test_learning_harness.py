"""Training on a time budget (`python -m experiments.restaurant --minutes M`,
`mpcpearl_jax.training.budget`): time-to-threshold, the eval schedule (fake trainer and clock),
option errors, and one real smoke run end to end."""

from __future__ import annotations

import json
import math

import pytest

from mpcpearl_jax.cli import args as cli_args
from mpcpearl_jax.cli import train as cli_train
from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.training import budget as learning
from mpcpearl_jax.training.run import Session


def main(argv, **kw):
    return cli_train.main("restaurant", argv, **kw)


def _point(minutes, it, test_sr, val_sr):
    return {
        "minutes": minutes,
        "grad_steps": it * 10,
        "iteration": it,
        "test_SR": test_sr,
        "val_SR": val_sr,
    }


def test_time_to_threshold_on_a_hand_made_curve():
    curve = [
        _point(0.0, 0, 0.0, 0.0),
        _point(1.0, 5, 0.0, float("nan")),
        _point(2.0, 9, 0.25, 0.1),
        _point(3.0, 14, 0.5, 0.3),  # exactly 0.5 counts for ">= 0.5"
        _point(4.0, 20, 0.4, 0.2),  # not monotone: the first crossing is what counts
        _point(5.0, 26, 0.8, 0.3),
    ]
    tt = learning.time_to_targets(curve)
    assert tt["test"]["first_success"] == {
        "minutes": 2.0,
        "grad_steps": 90,
        "iteration": 9,
        "value": 0.25,
    }
    assert tt["test"]["SR_0.5"]["minutes"] == 3.0 and tt["test"]["SR_0.5"]["grad_steps"] == 140
    assert tt["test"]["SR_0.75"]["iteration"] == 26
    assert tt["val"]["first_success"]["minutes"] == 2.0  # the NaN point is skipped
    assert tt["val"]["SR_0.5"] is None and tt["val"]["SR_0.75"] is None
    # first success is strict (> 0); thresholds are >=
    assert learning.time_to_threshold(curve[:2], "test_SR", 0.0, strict=True) is None
    assert learning.time_to_threshold(curve[:2], "test_SR", 0.0)["iteration"] == 0
    assert learning.time_to_threshold([], "test_SR", 0.5) is None
    rows = [{"iteration": 1, "train_s": 30.0, "train_success": 0.0}]
    rows.append({"iteration": 2, "train_s": 36.0, "train_success": 0.25})
    assert learning.first_train_success(rows, 20) == {
        "minutes": 0.6,
        "grad_steps": 40,
        "iteration": 2,
        "value": 0.25,
    }
    assert learning.eval_every_minutes(8, None) == 1.0
    assert learning.eval_every_minutes(1, 5) == 0.5  # at least one eval before the end
    label = learning.default_label("restaurant", "smoke", "sac", 0.2)
    assert label == "restaurant-smoke-sac-eps0.2"


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class _FakeTrainer:
    """iteration: 5 s the first time (compilation), then 1 s; evaluate: 10 s (off the clock)."""

    def __init__(self, clock, diverge_at=None):
        from mpcpearl_jax.config import preset

        self.cfg = preset("smoke")
        self.num_train, self.horizon = 120, 80
        self.clock, self.diverge_at = clock, diverge_at
        self.eval_tasks = []

    def iteration(self, state):
        from mpcpearl_jax.training.trainer import TrainingDiverged

        if state + 1 == self.diverge_at:
            raise TrainingDiverged("non-finite losses ['q_loss']")
        self.clock.t += 5.0 if state == 0 else 1.0
        log = {"iteration": state + 1, "train_success": 0.0, "train_mpc_share": 0.2}
        return state + 1, log | {"mpc_fallbacks": 1, "q_loss": 3.0}

    def evaluate(self, state, tasks=None, online=False):
        self.clock.t += 10.0
        self.eval_tasks.append(tasks)
        sr = min(1.0, state / 20)
        return {"SR": sr, "CFR": 1.0, "TT": 80.0, "SPL": 0.0, "MGD": 1.0, "return": -1.0 * state}


def test_train_for_schedule_with_a_fake_clock(tmp_path):
    clock = _Clock()
    trainer = _FakeTrainer(clock)
    log = tmp_path / "metrics.jsonl"
    state, points, info = learning.train_for(
        Session(trainer.cfg, tmp_path, trainer, 0),
        budget_s=30.0,
        every_s=10.0,
        val_tasks="VAL",
        clock=clock,
        on_point=None,
    )
    # train_s after iteration k: 5 + (k - 1); evaluations at 0, >= 10 s, >= 20 s, >= 30 s (end)
    assert [p["iteration"] for p in points] == [0, 6, 16, 26]
    assert [p["minutes"] * 60 for p in points] == [0.0, 10.0, 20.0, 30.0]  # evals off the clock
    assert state == 26 and info["iterations"] == 26 and info["stopped"] == "budget"
    assert info["train_s"] == 30.0 and info["eval_s"] == 80.0 and info["first_iteration_s"] == 5.0
    assert trainer.eval_tasks == [None, "VAL"] * 4  # test tasks, then the validation set
    assert points[-1]["wall_minutes"] * 60 == 30.0 + 80.0
    assert points[1]["grad_steps"] == 6 * trainer.cfg.train.updates_per_iteration
    assert points[1]["env_steps"] == learning.env_steps(trainer, 6) > 0 == points[0]["env_steps"]
    assert points[1]["train_mpc_share"] == 0.2 and points[1]["mpc_fallbacks"] == 1
    assert "q_loss" not in points[1] and "train_success" not in points[0]
    assert points[-1]["test_SR"] == 1.0 and points[-1]["val_SR"] == 1.0
    rows = [json.loads(x) for x in log.read_text().splitlines()]
    assert [r["iteration"] for r in rows] == list(range(1, 27))
    assert [r["iteration"] for r in rows if "test_SR" in r] == [6, 16, 26]


def test_train_for_stops_on_divergence(tmp_path):
    clock = _Clock()
    trainer = _FakeTrainer(clock, diverge_at=3)
    _, points, info = learning.train_for(
        Session(trainer.cfg, tmp_path, trainer, 0),
        budget_s=30.0,
        every_s=10.0,
        val_tasks=None,
        clock=clock,
        on_point=None,
    )
    assert info["stopped"].startswith("diverged") and info["iterations"] == 2
    assert len(points) == 1


def test_option_errors_are_one_line(tmp_path, capsys):
    a_file = tmp_path / "file"
    a_file.write_text("")
    assert main(["--preset", "smoke", "--minutes", "1", "--out", str(a_file)]) == 2
    err = capsys.readouterr().err.strip()
    assert str(a_file) in err and len(err.splitlines()) == 1
    argv = ["--preset", "smoke", "--minutes", "1", "--out", str(tmp_path / "x")]
    assert main(argv + ["--set", "train.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err
    for bad, flag in (
        (argv[:3] + ["0"] + argv[4:], "--minutes must be positive"),
        (argv + ["--eval-minutes", "-1"], "--eval-minutes must be positive"),
        (argv + ["--iterations", "3"], "--minutes and --iterations"),
        (argv + ["--resume", "--policy-only"], "--policy-only"),
        (["--preset", "smoke", "--eval-minutes", "1"], "give --minutes too"),
        (["--preset", "smoke", "--policy-only"], "give --minutes too"),
    ):
        assert main(bad) == 2, bad
        err = capsys.readouterr().err.strip()
        assert flag in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "x").exists()


def test_print_config_prints_the_resolved_config_and_trains_nothing(tmp_path, capsys):
    from mpcpearl_jax.config import ExperimentConfig, preset

    out = tmp_path / "never"
    assert main(["--preset", "recipe", "--eps", "0.1", "--print-config", "--out", str(out)]) == 0
    cfg = ExperimentConfig.from_json(capsys.readouterr().out)
    assert cfg.train.eps == 0.1 and cfg.pearl == preset("recipe").pearl and not out.exists()
    assert main(["--print-config", "--set", "pearl.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err


def test_help_config_lists_every_field_with_its_source_comment(capsys):
    """--help-config is generated from the config dataclasses' source: every --set field, its
    default, and the comment the source gives it."""
    import dataclasses

    from mpcpearl_jax.config import TrainConfig, chosen_elsewhere, override_sections

    with pytest.raises(SystemExit) as stop:
        cli_args.parser("restaurant").parse_args(["--help-config"])
    assert stop.value.code == 0
    text = capsys.readouterr().out
    for section, cls in override_sections(ExperimentConfig).items():
        for f in dataclasses.fields(cls):
            listed = f"{section}.{f.name} = " in text or f"\n  {f.name} = " in text
            if chosen_elsewhere(cls, f.name):  # the family (--env): not listed as settable
                assert not listed, f.name
            elif f.name not in ("pearl", "train", "mpc", "env_overrides"):
                assert listed, f.name
    assert "env.name = " not in text and "\n  env = " not in text
    assert "train.eps = 0.2: MPC probability on an event (0 = PEARL)" in text
    notes = cli_args.field_comments(TrainConfig)
    assert notes["iterations"] == ("", "")
    heading, text = notes["redraw_behaviours"]
    assert heading.startswith("extensions beyond the paper") and heading.endswith("each one)")
    assert text.startswith("behaviours re-drawn: each time")  # the heading's lines excluded
    assert notes["explore_start_share"][0] == ""  # a heading goes with the first field after it


def test_experiments_cli_is_unchanged():
    from mpcpearl_jax.cli.args import build_config, parser

    args = parser("restaurant").parse_args(
        ["--preset", "smoke", "--eps", "0.3", "--iterations", "7", "--algo", "sac", "--resume"]
        + ["--seeds", "2", "--seed", "5", "--no-progress", "--set", "train.t_update=3"]
    )
    cfg = build_config(args, "restaurant")
    assert (cfg.train.eps, cfg.train.iterations, cfg.train.t_update) == (0.3, 7, 3)
    assert (cfg.seeds, cfg.seed, cfg.pearl.use_context, args.resume) == (2, 5, False, True)
    assert parser("sidewalk").parse_args(["--data", "f.txt"]).data.name == "f.txt"


@pytest.fixture
def fast_compile():
    """Compile with few optimisations (the numbers of this smoke run mean nothing)."""
    import jax

    jax.config.update("jax_disable_most_optimizations", True)
    yield
    jax.config.update("jax_disable_most_optimizations", False)


@pytest.mark.slow  # (~45 s); the command itself: test_restaurant_cli_smoke
def test_smoke_run_writes_curve_policy_and_results(tmp_path, fast_compile, capsys):
    from mpcpearl_jax import load_policy

    out = tmp_path / "curve"
    argv = ["--preset", "smoke", "--eps", "0", "--minutes", "0.3", "--eval-minutes", "0.1"]
    assert main(argv + ["--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "time to target" in stdout and "| metric |" in stdout
    rec = json.loads((out / "curve.json").read_text())
    assert rec["label"] == "restaurant-smoke-pearl-eps0" and rec["stopped"] == "budget"
    assert rec["val_tasks"] == 24 and rec["test_tasks"] == 24 and rec["eval_protocol"] == "adapt"
    assert set(rec["time_to"]) == {"test", "val", "train"}
    assert set(rec["time_to"]["test"]) == {"first_success", "SR_0.5", "SR_0.75"}
    assert len(rec["loadavg_start_1m_5m_15m"]) == 3 and "cores_available" in rec["threads"]
    assert {"first_iteration_s", "train_s", "eval_s", "final_evaluation_s"} <= set(rec["timing"])
    assert rec["timing"]["train_s"] >= 0.3 * 60
    points = rec["points"]
    assert len(points) >= 2
    minutes = [p["minutes"] for p in points]
    assert minutes[0] == 0.0 and all(b > a for a, b in zip(minutes, minutes[1:], strict=False))
    assert points[-1]["iteration"] == rec["iterations"] >= 1
    for p in points:
        for split in ("test", "val"):
            for m in ("SR", "CFR", "TT", "SPL", "MGD", "return"):
                assert math.isfinite(p[f"{split}_{m}"]), (split, m)
        assert p["grad_steps"] == p["iteration"] * rec["updates_per_iteration"]
    assert {"train_success", "train_mpc_share", "env_steps"} <= set(points[-1])
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == rec["iterations"] and "test_SR" in rows[-1] and "val_SR" in rows[-1]
    assert rows[-1]["val_SR"] == points[-1]["val_SR"]
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["train"]["iterations"] == rec["iterations"] and cfg["train"]["eps"] == 0
    for name in ("curve.png", "results.json", "policy.msgpack", "trajectory_test0.png"):
        assert (out / name).is_file(), name
    assert (out / "checkpoints").is_dir()
    policy = load_policy(out)
    import jax.numpy as jnp

    act = policy.act(jnp.zeros((policy.obs_dim,)), policy.prior_z())
    assert act.shape == (2,) and bool(jnp.all(jnp.abs(act) <= 1))


def test_the_old_command_name_runs_the_same_program():
    """`python -m experiments.learning` (the name recorded with older results) is the training
    command, taking its family from --env or from --config's run."""
    import experiments.learning

    assert experiments.learning.main is cli_train.main
    args = cli_args.parse_args("restaurant", ["--env", "sidewalk", "--data", "f.txt"])
    assert args.env == "sidewalk" and args.data.name == "f.txt"
