"""A task family of one's own (examples/corridor.py, docs/custom_tasks.md): registered by
importing its module, trained from Python and from the command line with --env MODULE:NAME."""

import json

import jax
import pytest

from mpcpearl_jax.envs import env_names, load_family, make_env, make_tasks

# a tiny budget on top of the smoke preset: one iteration of small networks, every part of a run
# still exercised (the MPC included); both trainings build the same programs, which the test
# session's compilation cache (conftest.py) then compiles once
TINY = {
    "train.iterations": 1,
    "train.initial_episodes": 1,
    "train.tasks_per_iteration": 2,
    "train.updates_per_iteration": 5,
    "train.eval_interval": 0,
    "train.rl_capacity": 400,
    "train.eps": 0.5,
    "pearl.hidden": (16, 16),
    "pearl.encoder_hidden": (16,),
    "pearl.meta_batch": 2,
    "pearl.batch_size": 16,
    "pearl.context_size": 8,
}


@pytest.fixture
def small_corridor(monkeypatch):
    """The corridor with fewer tasks per split (8 training, 4 of each other), for speed."""
    from examples import corridor

    for split, n in {"train": 8, "val": 4, "test": 4, "ood": 4}.items():
        monkeypatch.setitem(corridor.SPLIT_SIZES, split, n)
    return corridor


def test_importing_the_module_registers_the_family():
    from examples import corridor

    assert load_family("examples.corridor:corridor") == corridor.NAME in env_names()
    tasks = make_tasks("corridor", "train")
    assert tasks.human_pos.shape == (40, 81, 3, 2) and tasks.static_lo.shape == (40, 2, 2)
    assert make_env("corridor").obs_dim(tasks) == 13  # pose 3 + 3 people x 2 + 2 pillars x 2
    # redrawn people keep the task's pillars, start and goal
    again = corridor.redraw(0, corridor.CONFIG, [3, 5], (1, 2))
    assert (again.start == tasks.start[jax.numpy.array([3, 5])]).all()
    assert not (again.human_pos == tasks.human_pos[jax.numpy.array([3, 5])]).all()


def test_a_python_session_builds_the_trainer_on_the_family(tmp_path, small_corridor):
    """The Python route of `corridor.train` up to training (the fast variant of the next test):
    the smoke preset resolved for the family, a run session opened on it."""
    from mpcpearl_jax.config import resolve, validate
    from mpcpearl_jax.training.run import open_session

    cfg = validate(resolve("smoke", "corridor", changes=TINY))
    assert cfg.env == "corridor" and cfg.mpc.v_max is None  # the family's MPC default
    with open_session(cfg, tmp_path / "run") as session:
        assert session.trainer.obs_dim == 13 and session.done == 0
    assert (tmp_path / "run" / "config.json").is_file()


@pytest.mark.slow  # a second training of about a minute; the command line's test trains the same
def test_train_from_python(tmp_path, small_corridor):
    res = small_corridor.train(tmp_path / "run", "smoke", TINY)
    assert res["env"] == "corridor" and {"SR", "CFR"} <= set(res["test_adapt"])
    assert "SR" in res["ood_adapt"]  # the family's faster people
    log = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert len(log) == 1 and log[0]["mpc_rows"] > 0  # the MPC acted on the corridor's people
    assert (tmp_path / "run" / "trajectory_test0.png").is_file()


@pytest.mark.slow  # the command-line path of --env MODULE:NAME (~70 s); the Python API: fast
def test_train_from_the_command_line(tmp_path, capsys, small_corridor):
    from mpcpearl_jax.cli.train import main

    out = tmp_path / "cli"
    argv = ["--env", "examples.corridor:corridor", "--preset", "smoke", "--out", str(out)]
    sets = [f"{k}={json.dumps(v)}" for k, v in TINY.items()]
    argv += ["--no-progress"] + [x for kv in sets for x in ("--set", kv)]
    assert main("restaurant", argv) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("[corridor] MPC-PEARL 0.5") and "this run: MPC-PEARL 0.5" in printed
    res = json.loads((out / "results.json").read_text())
    assert res["env"] == "corridor" and "SR" in res["test_adapt"] and "SR" in res["ood_adapt"]
    log = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert len(log) == 1 and log[0]["mpc_rows"] > 0  # the MPC acted on the corridor's people


@pytest.mark.parametrize(
    "spec, names",
    [
        ("examples.nosuch:corridor", "no module named 'examples.nosuch'"),
        ("examples.corridor:nosuch", "registered no family 'nosuch'"),
        ("nosuch", "no such task family"),
        ("examples.corridor:", "expected MODULE:NAME"),
    ],
)
def test_a_missing_module_or_family_is_one_line_naming_the_flag(spec, names, capsys):
    from mpcpearl_jax.cli.train import main

    assert main("restaurant", ["--env", spec, "--preset", "smoke"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: --env {spec}: ") and names in err and "\n" not in err
