"""The paper's own restaurant scenarios as a task source (envs/restaurant/scenarios.py): the
authors' files when ../shared/data has them, and small synthetic files written here (always)."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax import make_env, make_tasks
from mpcpearl_jax.envs.restaurant import scenarios as sc
from mpcpearl_jax.errors import DataFormatError

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mpc-pearl-scenarios"
# the digests the shared data's README gives for the authors' files
MAIN_SHA = "0302f2c8963dc6972e63566ba220ea3502e5d3f4f68ef5d40171f1eda663a356"
OOD_SHA = "c7ef6f959db97c1163f62d097937a9ded8e2dd414a7a72577ecb822b50e6ab4d"
needs_shared = pytest.mark.skipif(
    not (SHARED / sc.MAIN_FILE).is_file(), reason="the authors' scenarios are not in ../shared"
)
RUN = Path(__file__).resolve().parents[1] / "results" / "restaurant" / "main-default"


def _people(n: int, seed: int) -> np.ndarray:
    """(n, 2, 81, 6) float64 positions inside the arena (the authors' layout)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-4.5, 4.5, size=(n, 2, 81, 6))


def write_scenarios(root: Path, main=None, ood=None, with_ood: bool = True) -> Path:
    (root / "scenarios").mkdir(parents=True, exist_ok=True)
    np.save(root / sc.MAIN_FILE, _people(205, 0) if main is None else main)
    if with_ood:
        (root / "scenarios_out_of_distribution").mkdir(exist_ok=True)
        np.save(root / sc.OOD_FILE, _people(25, 1) if ood is None else ood)
    return root


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    return write_scenarios(tmp_path_factory.mktemp("scen"))


def test_split_ids_are_the_authors_split_and_a_fixed_val_hold_out():
    assert sc.scenario_ids("train") == list(range(180))
    assert sc.scenario_ids("test") == list(range(180, 205))
    assert sc.scenario_ids("ood") == list(range(25))
    val = sc.scenario_ids("val")
    assert val == list(range(150, 180))
    held = sc.scenario_ids("train", hold_out_val=True)
    assert held == list(range(150)) and not set(held) & set(val)
    # six val tasks per table configuration
    assert np.bincount(np.asarray(val) % 5).tolist() == [6] * 5


def test_synthetic_tasks_equal_the_file(synthetic):
    x = np.load(synthetic / sc.MAIN_FILE)
    sizes = {"train": 180, "val": 30, "test": 25, "ood": 25}
    for split, n in sizes.items():
        t = make_tasks("restaurant", split, scenarios=synthetic)
        assert t.human_pos.shape == (n, 81, 6, 2)
        assert bool(np.all(t.human_mask))
        np.testing.assert_allclose(t.start, np.tile([-4.5, 4.5, -np.pi / 8], (n, 1)), atol=1e-6)
        np.testing.assert_allclose(t.goal, np.tile([3.5, -3.5], (n, 1)))
        np.testing.assert_allclose(t.static_radius, 0.5)
    t = make_tasks("restaurant", "test", scenarios=synthetic)
    for j, i in enumerate(range(180, 205)):
        # (x/y, step, person) -> (step, person, x/y), float32
        np.testing.assert_allclose(t.human_pos[j], np.transpose(x[i], (1, 2, 0)), atol=1e-6)
    held = make_tasks("restaurant", "train", scenarios=synthetic, hold_out_val=True)
    assert held.human_pos.shape[0] == 150


def test_tables_follow_the_authors_configurations(synthetic):
    # task i uses configuration i % 5; grid centres (-2.5, 2.5) ... (2.5, -2.5), row-major
    configs = [(0, 2, 4, 5, 7), (0, 4, 5, 6, 8), (1, 3, 4, 5, 8), (1, 2, 3, 4, 7), (2, 3, 4, 6, 7)]
    grid = [(x, y) for y in (2.5, 0.0, -2.5) for x in (-2.5, 0.0, 2.5)]
    t = make_tasks("restaurant", "test", scenarios=synthetic)
    for j, i in enumerate(range(180, 205)):
        want = np.array([grid[g] for g in configs[i % 5]])
        np.testing.assert_allclose(t.static_lo[j], want)
        np.testing.assert_allclose(t.static_hi[j], want)
    ood = make_tasks("restaurant", "ood", scenarios=synthetic)
    for j in range(25):
        want = np.array([grid[g] for g in configs[j % 5]])
        want[:, 0] = sc.OOD_TABLE_X[j % 5]
        np.testing.assert_allclose(ood.static_lo[j], want, atol=1e-6)
        assert np.all(want[:, 0] <= np.array([grid[g] for g in configs[j % 5]])[:, 0])


@needs_shared
def test_the_authors_files():
    assert sc.scenario_digests(SHARED) == {sc.MAIN_FILE: MAIN_SHA, sc.OOD_FILE: OOD_SHA}
    x = np.load(SHARED / sc.MAIN_FILE)
    assert x.shape == (205, 2, 81, 6)
    t = make_tasks("restaurant", "test", scenarios=SHARED)
    assert t.human_pos.shape == (25, 81, 6, 2)
    # task 180: configuration 0 (180 % 5), people as in the file
    np.testing.assert_allclose(t.human_pos[0], np.transpose(x[180], (1, 2, 0)), atol=1e-6)
    c0 = np.array([(-2.5, 2.5), (2.5, 2.5), (0.0, 0.0), (2.5, 0.0), (0.0, -2.5)])
    np.testing.assert_allclose(t.static_lo[0], c0)
    ood = make_tasks("restaurant", "ood", scenarios=SHARED)
    np.testing.assert_allclose(
        ood.static_lo[0, :, 0], [-3.303, 1.633, -0.569, 1.844, -0.999], atol=1e-6
    )
    assert make_tasks("restaurant", "train", scenarios=SHARED).human_pos.shape[0] == 180


def _error(path: Path, split: str = "test", **kw) -> str:
    with pytest.raises((DataFormatError, FileNotFoundError)) as e:
        make_tasks("restaurant", split, scenarios=path, **kw)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


def test_bad_folders_and_files_give_one_line_naming_the_file(tmp_path):
    assert "no such directory" in _error(tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    assert "scenarios/X.npy" in _error(tmp_path / "empty") and "no such file" in _error(
        tmp_path / "empty"
    )
    no_ood = write_scenarios(tmp_path / "no-ood", with_ood=False)
    make_tasks("restaurant", "test", scenarios=no_ood)  # the OOD file is optional...
    assert sc.OOD_FILE in _error(no_ood, "ood")  # ...until the OOD split is asked for

    cases = {
        "shape": (_people(204, 0), "shape (204, 2, 81, 6)"),
        "steps": (_people(205, 0)[:, :, :80], "expected (205, 2, 81, 6)"),
        "dtype": (np.zeros((205, 2, 81, 6), np.int64), "dtype int64"),
        "outside": (_people(205, 0), "outside the arena"),
        "nan": (_people(205, 0), "non-finite"),
    }
    cases["outside"][0][7, 1, 40, 3] = 5.5
    cases["nan"][0][9, 0, 3, 2] = np.nan
    for name, (array, want) in cases.items():
        root = write_scenarios(tmp_path / name, main=array)
        msg = _error(root)
        assert want in msg and str(root / sc.MAIN_FILE) in msg, (name, msg)
    assert "task 7" in _error(tmp_path / "outside") and "task 9" in _error(tmp_path / "nan")

    garbage = tmp_path / "garbage"
    (garbage / "scenarios").mkdir(parents=True)
    (garbage / sc.MAIN_FILE).write_bytes(b"not an array")
    assert "not a NumPy" in _error(garbage)


def test_a_recorded_digest_is_checked(tmp_path, synthetic):
    digests = sc.scenario_digests(synthetic)
    make_tasks("restaurant", "test", scenarios=synthetic, scenario_sha256=digests)
    other = write_scenarios(tmp_path / "other", main=_people(205, 5))
    msg = _error(other, scenario_sha256=digests)
    assert "sha256" in msg and "not the file the run was trained on" in msg


def test_generator_options_are_refused_with_scenarios(synthetic):
    with pytest.raises(TypeError, match="train_behaviours"):
        make_tasks("restaurant", "train", scenarios=synthetic, train_behaviours=30)


# ------------------------------------------------------------------------ command lines
def test_config_records_the_source_and_refuses_redraw(synthetic):
    from mpcpearl_jax.cli.args import build_config, parser
    from mpcpearl_jax.config import validate
    from mpcpearl_jax.errors import ConfigError

    args = parser("restaurant").parse_args(["--scenarios", str(synthetic), "--hold-out-val"])
    cfg = build_config(args, "restaurant")
    assert cfg.task_options["scenarios"] == str(synthetic)
    assert cfg.task_options["hold_out_val"] is True
    assert cfg.task_options["scenario_sha256"] == sc.scenario_digests(synthetic)
    assert cfg.train.redraw_behaviours is False  # the default preset keeps the fixed crowds
    validate(cfg)
    explicit = parser("restaurant").parse_args(
        ["--preset", "cpu-explore", "--scenarios", str(synthetic)]
    )
    with pytest.raises(ConfigError, match="redraw_behaviours"):
        validate(build_config(explicit, "restaurant"))
    with pytest.raises(ConfigError, match="--hold-out-val"):
        build_config(parser("restaurant").parse_args(["--hold-out-val"]), "restaurant")


def test_resolve_keeps_the_recorded_crowds_of_the_scenarios(synthetic):
    """`config.resolve` with the paper's scenarios: the default preset keeps their fixed crowds;
    the validation set is tasks 150-179 when they were held out of training, else (the run has
    trained on them) the first 24 training tasks."""
    from mpcpearl_jax.config import resolve, validate
    from mpcpearl_jax.envs import tasks_for, validation_tasks
    from mpcpearl_jax.errors import ConfigError

    held = validate(resolve("default", scenarios=synthetic, hold_out_val=True))
    assert held.train.redraw_behaviours is False and held.train.explore_start_share == 0.5
    assert held.task_options == sc.scenario_options(synthetic, hold_out_val=True)
    val, what = validation_tasks(held)
    assert val.num_tasks == 30 and "scenarios 150-179" in what
    every = validate(resolve("default", scenarios=synthetic))
    val, what = validation_tasks(every)
    first = jax.tree_util.tree_map(lambda x: x[:24], tasks_for(every, "train"))
    jax.tree_util.tree_map(np.testing.assert_array_equal, val, first)
    assert "first 24 training tasks" in what
    with pytest.raises(ConfigError, match="redraw_behaviours"):
        validate(resolve("cpu-explore", scenarios=synthetic))
    with pytest.raises(ConfigError, match="restaurant tasks"):
        resolve("default", "sidewalk", scenarios=synthetic)


def test_training_cli_on_a_bad_folder_writes_nothing(tmp_path, capsys):
    from mpcpearl_jax.cli.train import main

    out = tmp_path / "run"
    rc = main("restaurant", ["--preset", "smoke", "--scenarios", str(tmp_path), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and "scenarios/X.npy" in err
    assert not out.exists()


def test_evaluate_a_committed_policy_on_scenarios(tmp_path, synthetic, capsys):
    from mpcpearl_jax.cli import evaluate

    out = tmp_path / "ev"
    argv = [str(RUN), "--scenarios", str(synthetic), "--split", "ood", "--tasks", "0-2"]
    assert evaluate.main([*argv, "--figures", "none", "--out", str(out)]) == 0
    rec = json.loads((out / "results.json").read_text())
    assert rec["scenarios"]["scenarios"] == str(synthetic)
    assert rec["scenarios"]["scenario_sha256"] == sc.scenario_digests(synthetic)
    assert rec["task_seed"] is None and rec["tasks"] == [0, 1, 2]
    assert "the paper's scenarios" in capsys.readouterr().out
    # a task-set seed means nothing for a fixed set of tasks; a bad folder is one line
    for bad in (
        [str(RUN), "--scenarios", str(synthetic), "--task-seeds", "1-2"],
        [str(RUN), "--scenarios", str(synthetic), "--task-seed", "3"],
        [str(RUN), "--scenarios", str(tmp_path / "absent")],
    ):
        assert evaluate.main(bad) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and "\n" not in err


@pytest.mark.slow  # (~11 s)
def test_gp_mpc_cli_on_scenarios(tmp_path, synthetic, capsys):
    from experiments import gp_mpc

    out = tmp_path / "g"
    argv = ["--scenarios", str(synthetic), "--split", "test", "--max-tasks", "1"]
    assert gp_mpc.main([*argv, "--out", str(out)]) == 0
    rec = json.loads((out / "restaurant_test_tasks0-1.json").read_text())
    assert rec["scenarios"]["scenarios"] == str(synthetic) and rec["seed"] is None
    assert gp_mpc.main(["--scenarios", str(tmp_path / "absent"), "--out", str(out)]) == 2
    assert "no such directory" in capsys.readouterr().err


@pytest.mark.slow  # (~15 s)
def test_gp_mpc_runs_a_range_of_the_180_training_scenarios(tmp_path, synthetic, capsys):
    """`experiments.gp_mpc --scenarios DIR --split train --tasks 178:180`: the last two of the
    180 training scenarios, recorded with their range in a file of their own."""
    from experiments import gp_mpc

    out = tmp_path / "g"
    argv = ["--scenarios", str(synthetic), "--split", "train", "--tasks", "178:180"]
    assert gp_mpc.main([*argv, "--out", str(out)]) == 0
    assert "2 tasks (178 to 179)" in capsys.readouterr().out
    rec = json.loads((out / "restaurant_train_tasks178-180.json").read_text())
    assert rec["split"] == "train" and rec["tasks"] == [178, 180]
    assert len(rec["per_task"]["in_goal"]) == 2
    assert (out / "restaurant_train_tasks178-180_task178.png").is_file()  # named after it


@pytest.mark.slow  # a training on the authors' scenarios (~60 s); their loading is tested fast
def test_a_run_trained_on_scenarios_records_its_source_and_evaluates(tmp_path, capsys):
    """One smoke iteration on synthetic scenarios (no OOD file) with the val hold-out: the run
    records its source, its final evaluation says the OOD file is missing (not scoring the
    generated OOD tasks), `load_policy` and `experiments.evaluate` work on it (val allowed: held
    out), and a resume on a changed file is refused by its recorded sha256."""
    from mpcpearl_jax import load_policy
    from mpcpearl_jax.cli import evaluate
    from mpcpearl_jax.cli.train import main

    scen = write_scenarios(tmp_path / "scen", with_ood=False)
    out = tmp_path / "run"
    argv = ["--preset", "smoke", "--eps", "0", "--no-progress", "--out", str(out)]
    argv += ["--scenarios", str(scen), "--hold-out-val"]
    argv += ["--set", "train.tasks_per_iteration=2", "--set", "train.eval_interval=0"]
    assert main("restaurant", [*argv, "--iterations", "1"]) == 0
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["task_options"]["scenario_sha256"] == sc.scenario_digests(scen)
    res = json.loads((out / "results.json").read_text())
    # the run's OOD split is the scenarios' (here absent), never the generated crowds' OOD tasks
    assert sc.OOD_FILE in res["ood_adapt"]["skipped"] and set(res["test_adapt"]) >= {"SR"}
    policy = load_policy(out)
    assert policy.config.task_options == cfg["task_options"]
    tasks = make_tasks("restaurant", "test", scenarios=scen)
    env = make_env("restaurant", **policy.config.env_overrides)
    task0 = jax.tree_util.tree_map(lambda x: x[0], tasks)
    obs, _ = env.reset(jax.random.PRNGKey(0), task0)
    action = policy.act(obs, policy.prior_z())
    assert action.shape == (2,) and bool(jnp.all(jnp.abs(action) <= 1))
    capsys.readouterr()
    assert evaluate.main([str(out), "--split", "val", "--figures", "none"]) == 0
    rec = json.loads((out / "eval" / "policy-scenarios-val" / "results.json").read_text())
    assert len(rec["tasks"]) == 30
    # the file changes under the run: its tasks are no longer the recorded ones
    np.save(scen / sc.MAIN_FILE, _people(205, 9))
    capsys.readouterr()
    assert main("restaurant", [*argv, "--iterations", "2", "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert "sha256" in err and "\n" not in err


def test_a_bad_ood_file_is_found_before_training(tmp_path, synthetic, capsys):
    """A bad out-of-distribution scenario file used to be found only at the final evaluation,
    after training, and its column silently left out; it is refused before anything is
    written."""
    import shutil

    from mpcpearl_jax.cli.train import main

    folder = tmp_path / "scen"
    shutil.copytree(synthetic, folder)
    (folder / sc.OOD_FILE).write_bytes(b"not a numpy file")
    out = tmp_path / "run"
    rc = main("restaurant", ["--preset", "smoke", "--scenarios", str(folder), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and "scenarios_out_of_distribution/X.npy" in err
    assert not out.exists()
