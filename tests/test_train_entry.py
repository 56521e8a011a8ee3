"""The one entry to training, `mpcpearl_jax.train`, and what the training commands build on it:
its arguments checked before anything is created, a stop during the iteration that ends the
training, a resume that reads the run's own config, and the line a resume prints when it only
evaluated."""

from __future__ import annotations

import dataclasses
import os
import signal

import pytest

from mpcpearl_jax.config import ExperimentConfig, preset, resolve
from mpcpearl_jax.errors import ConfigError


@pytest.mark.parametrize(
    "cfg, expected",
    [
        ("smoke", "mpcpearl_jax.config.resolve('smoke')"),
        (None, "not NoneType"),
        ({"env": "restaurant"}, "not dict"),
    ],
)
def test_a_wrong_config_type_is_one_sentence_naming_what_train_expects(tmp_path, cfg, expected):
    import mpcpearl_jax

    out = tmp_path / "run"
    with pytest.raises(TypeError) as e:
        mpcpearl_jax.train(cfg, out)
    text = str(e.value)
    assert text.startswith("mpcpearl_jax.train: cfg must be a run config") and expected in text
    assert "\n" not in text and not out.exists()


@pytest.mark.parametrize(
    "minutes, error, needle",
    [
        (-1, ValueError, "minutes must be positive and finite, got -1"),
        (0, ValueError, "got 0"),
        (float("nan"), ValueError, "got nan"),
        ("5", TypeError, "minutes must be a number of minutes of training"),
        (True, TypeError, "not bool True"),
    ],
)
def test_a_bad_time_budget_is_refused_before_the_folder_is_made(tmp_path, minutes, error, needle):
    """minutes=-1 used to write a run of 0 iterations; minutes="5" created the folder, then
    raised a TypeError, and the folder left behind blocked the same out."""
    import mpcpearl_jax

    out = tmp_path / "run"
    with pytest.raises(error, match=needle):
        mpcpearl_jax.train(preset("smoke"), out, minutes=minutes)
    assert not out.exists()


def test_other_wrong_arguments_name_what_is_expected(tmp_path):
    import mpcpearl_jax
    from mpcpearl_jax.training.final import TrainOptions

    cfg = preset("smoke")
    with pytest.raises(TypeError, match="out must be a folder path"):
        mpcpearl_jax.train(cfg, 3)
    with pytest.raises(TypeError, match="options must be a mpcpearl_jax.training.options.Train"):
        mpcpearl_jax.train(cfg, tmp_path / "a", options={"resume": True})
    with pytest.raises(ValueError, match="resume or overwrite, not both"):
        mpcpearl_jax.train(cfg, tmp_path / "b", options=TrainOptions(resume=True, overwrite=True))
    with pytest.raises(ValueError, match="policy_only applies to an MPC-PEARL time budget"):
        mpcpearl_jax.train(cfg, tmp_path / "c", options=TrainOptions(policy_only=True))
    assert list(tmp_path.iterdir()) == []


def test_grbal_refuses_a_negative_budget_before_training(tmp_path, capsys):
    """`experiments.grbal --minutes -3` used to train and write a run."""
    from experiments import grbal

    out = tmp_path / "run"
    assert grbal.main(["--preset", "smoke", "--minutes", "-3", "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == "error: --minutes must be positive, got -3.0"
    assert not out.exists()


class _Trainer:
    """Three iterations of nothing; a stop signal arrives to this process during the last."""

    def __init__(self, total: int):
        self.total = total

    def iteration(self, state, stop=None):
        n = state + 1
        if n == self.total:
            os.kill(os.getpid(), signal.SIGINT)  # handled by the session's stop flag
        return n, {"iteration": n}


@dataclasses.dataclass
class _State:
    iteration: int = 0


def test_a_stop_during_the_iteration_that_ends_training_stops_the_run(tmp_path):
    """A stop signal during the last iteration (GrBAL on a time budget: its first iteration is
    its last) used to be lost: the loop ended as if done, and the command ran the whole final
    evaluation and exited 0. The session now raises RunInterrupted, the iteration saved."""
    from mpcpearl_jax.training.run import RunInterrupted, Session

    saved = []
    sess = Session(preset("smoke"), tmp_path, _Trainer(3), 0)
    with pytest.raises(RunInterrupted) as e:
        sess.train(
            until=lambda p: p.iterations >= 3,
            save=lambda i, state: saved.append(i),
            handle_sigint=True,
        )
    assert e.value.iteration == 3 and saved == [3]
    assert sess.progress.stopped == "interrupted"


def _resume_args(out, *extra):
    from mpcpearl_jax.cli.args import parser

    return parser("restaurant").parse_args(["--resume", "--out", str(out), *extra])


def test_a_resume_reads_the_runs_own_config(tmp_path):
    """`--resume --out RUN` for a run started with --preset smoke used to build the default
    preset's config and fail with 22 differing fields; it continues the run's own config."""
    from mpcpearl_jax.cli.args import build_config
    from mpcpearl_jax.runfolder import save_config

    run_cfg = resolve("smoke", "restaurant", changes={"train.iterations": 3})
    save_config(tmp_path, run_cfg)
    args = _resume_args(tmp_path)
    cfg = build_config(args, "restaurant")
    assert isinstance(cfg, ExperimentConfig) and cfg.to_dict() == run_cfg.to_dict()
    assert args.preset == "smoke"  # printed on the command's first line
    more = build_config(_resume_args(tmp_path, "--iterations", "5"), "restaurant")
    assert more.train.iterations == 5 and more.train.updates_per_iteration == (
        run_cfg.train.updates_per_iteration
    )


def test_a_resume_with_another_preset_names_the_runs_preset(tmp_path):
    from mpcpearl_jax.cli.args import build_config
    from mpcpearl_jax.runfolder import save_config

    save_config(tmp_path, resolve("smoke", "restaurant"))
    with pytest.raises(ConfigError) as e:
        build_config(_resume_args(tmp_path, "--preset", "default"), "restaurant")
    text = str(e.value)
    assert "the run was started from preset smoke" in text
    assert f"--resume --out {tmp_path} alone" in text and "\n" not in text


def test_a_resume_that_only_evaluates_says_what_the_run_trained():
    """A run stopped during its final evaluation, resumed: the line under the results used to
    say '0 iteration(s) ... trained in 0.0 min'."""
    from mpcpearl_jax.cli.train import trained_line

    cfg = resolve("smoke", "restaurant", changes={"train.iterations": 1})
    line = trained_line(cfg, 0.0, start=1, info={"train_s": 90.0})
    assert "0 iteration(s)" not in line
    assert "1 iteration(s)" in line and "trained in 1.5 min before this resume" in line
    fresh = trained_line(cfg, 60.0, start=0, info={"train_s": 60.0})
    assert "1 iteration(s)" in fresh and "trained in 1.0 min on" in fresh


def test_a_grbal_resume_reads_the_runs_own_config(tmp_path):
    from mpcpearl_jax.cli.args import build_config, config_from_argv, parse_args
    from mpcpearl_jax.grbal.config import GrbalExperimentConfig

    def build(argv):  # as the grbal command builds it
        args = parse_args("restaurant", argv, algorithm="grbal")
        return args, build_config(args, "restaurant", algorithm="grbal")

    run_cfg = resolve("smoke", "sidewalk", config_type=GrbalExperimentConfig)
    (tmp_path / "config.json").write_text(run_cfg.to_json())
    args, cfg = build(["--resume", "--out", str(tmp_path)])
    assert cfg.to_dict() == run_cfg.to_dict()
    assert (args.env, args.preset) == ("sidewalk", "smoke")  # printed on the first line
    assert build(["--resume", "--out", str(tmp_path), "--iterations", "9"])[1].grbal.iterations == 9
    # the run's own preset named again: the same run; another one: one line naming the run's
    assert build(["--resume", "--out", str(tmp_path), "--preset", "smoke"])[1] == cfg
    with pytest.raises(ConfigError, match="started from preset smoke; --preset cpu"):
        build(["--resume", "--out", str(tmp_path), "--preset", "cpu"])
    # the lab's campaigns build it the same way
    assert config_from_argv("grbal", ["--resume", "--out", str(tmp_path)]) == cfg
    fresh = config_from_argv("grbal", ["--env", "sidewalk", "--preset", "smoke"])
    assert fresh == resolve("smoke", "sidewalk", config_type=GrbalExperimentConfig)


def test_an_algorithms_own_command_takes_its_options_from_its_registration():
    """`experiments.grbal`'s options come from the registered algorithm: its families, presets,
    --set sections, run folder and line per iteration; the options of the task families'
    commands it lacks read as not given."""
    from mpcpearl_jax import algorithms
    from mpcpearl_jax.cli.args import parser

    grbal = algorithms.get("grbal")
    p = parser(algorithm="grbal", description="GrBAL")
    actions = {a.dest: a for a in p._actions}
    assert p.prog == "python -m experiments.grbal"
    assert tuple(actions["env"].choices) == grbal.families == ("restaurant", "sidewalk")
    assert actions["preset"].choices == sorted(grbal.presets)
    assert "grbal.FIELD, env.FIELD or a top-level field" in actions["set"].help
    assert actions["out"].help == "run directory (default runs/<env>-<preset>-grbal)"
    assert actions["no_progress"].help == "no line per iteration"
    assert actions["iterations"].help == grbal.iterations_help
    assert not {"eps", "algo", "label", "config", "tensorboard", "debug"} & set(actions)
    args = p.parse_args([])
    assert (args.label, args.config, args.tensorboard, args.debug) == (None, None, False, False)
    family = {a.dest: a for a in parser("restaurant")._actions}
    assert family["out"].help == "run directory (default runs/<label>)"
    assert family["iterations"].help == "meta-training iterations"
