"""`mpcpearl_jax.evaluate`: the evaluation command's results as a library call, and its
arguments' errors in one line naming the argument."""

import json
from pathlib import Path

import pytest

import mpcpearl_jax
from mpcpearl_jax.cli.evaluate import main
from mpcpearl_jax.evaluation.plan import EvaluationError

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2"


def _without_wall(path: Path) -> dict:
    record = json.loads(path.read_text())
    record.pop("wall_s")
    return record


def test_the_call_returns_and_writes_what_the_command_writes(tmp_path, capsys):
    argv = [str(RUN), "--split", "val", "--tasks", "0-2", "--figures", "none"]
    assert main([*argv, "--out", str(tmp_path / "cli")]) == 0
    capsys.readouterr()
    ev = mpcpearl_jax.evaluate(RUN, split="val", tasks=[0, 1, 2], figures="none")
    assert ev.out is None and ev.written == []  # nothing written without out
    written = mpcpearl_jax.evaluate(RUN, split="val", tasks="0:3", out=tmp_path / "lib")
    assert written.written[0] == tmp_path / "lib" / "results.json"
    assert [p.name for p in written.written[1:]] == [f"trajectory_val{t}.png" for t in range(3)]
    cli = _without_wall(tmp_path / "cli" / "results.json")
    assert _without_wall(written.written[0]) == cli
    record = json.loads(json.dumps({k: v for k, v in ev.record.items() if k != "wall_s"}))
    assert record == cli
    assert ev.metrics == ev.record["metrics"] and ev.result["position"].shape[:2] == (1, 3)
    assert capsys.readouterr().out == ""  # the library prints nothing


def test_loaded_policies_evaluate_as_their_run_folder():
    from mpcpearl_jax import load_policy

    folder = mpcpearl_jax.evaluate(RUN, split="val", tasks="0-1", seed_index=0)
    loaded = mpcpearl_jax.evaluate([load_policy(RUN, 0)], split="val", tasks="0-1")
    assert loaded.record["metrics"] == folder.record["metrics"]
    assert loaded.record["run"] is None and folder.record["run"] == str(RUN)


@pytest.mark.parametrize(
    "kwargs,start",
    [
        ({"tasks": "0-99"}, "tasks: task(s) [24, 25, 26] and 73 more out of range"),
        ({"tasks": "3:1"}, "tasks '3:1': the range 3:1 is empty"),
        ({"tasks": "x"}, "tasks 'x': expected numbers like 0,3,5"),
        ({"tasks": "none"}, "tasks: no task selected"),
        ({"task_seeds": "5-1"}, "task_seeds '5-1': the range 5-1 is reversed"),
        ({"task_seeds": "0-1000"}, "task_seeds 0-1000: 1001 task sets; at most 100"),
        ({"task_seed": 1, "task_seeds": "1-2"}, "give task_seed or task_seeds, not both"),
        ({"split": "nosuch"}, "split 'nosuch': one of train"),
        ({"scenarios": "/nonexistent/folder"}, "scenarios: "),
        ({"env": "sidewalk", "scenarios": "x"}, "scenarios: the paper's scenarios are"),
        ({"figures": "5", "tasks": "0-1"}, "figures: task(s) [5] are not evaluated (see tasks)"),
        ({"perturb": "delay=x"}, "perturb 'delay=x': delay must be an int"),
        ({"controller": "nosuch"}, "controller 'nosuch': one of policy, gp-mpc, policy+mpc"),
        ({"controller": "policy"}, "controller policy needs a run directory (run)"),
        ({"mpc": ["alpha=2"]}, "mpc: "),
        ({"preset": "nosuch"}, "preset: unknown preset 'nosuch'"),
    ],
)
def test_a_bad_task_source_or_argument_is_one_line_naming_it(kwargs, start, tmp_path):
    kwargs = {"controller": "gp-mpc", "split": "test", **kwargs}
    with pytest.raises(EvaluationError) as e:
        mpcpearl_jax.evaluate(out=tmp_path / "o", **kwargs)
    assert str(e.value).startswith(start) and "\n" not in str(e.value), str(e.value)
    assert not (tmp_path / "o").exists()  # checked before the output folder is made


def test_the_command_spells_the_same_errors_with_its_flags(tmp_path, capsys):
    out = str(tmp_path / "o")
    assert main(["--controller", "gp-mpc", "--tasks", "0-99", "--out", out]) == 2
    assert capsys.readouterr().err.startswith("error: --tasks: task(s) [24, 25, 26]")
    assert main(["--controller", "gp-mpc", "--set", "alpha=2", "--out", out]) == 2
    assert capsys.readouterr().err.startswith("error: --set: ")
    (tmp_path / "o").mkdir(exist_ok=True)
    (tmp_path / "o" / "results.json").write_text("{}")
    with pytest.raises(EvaluationError, match="pass overwrite=True to replace it"):
        mpcpearl_jax.evaluate(controller="gp-mpc", out=out)
    assert main(["--controller", "gp-mpc", "--out", out]) == 2
    assert "pass --overwrite to replace it, or choose another --out" in capsys.readouterr().err


def test_the_options_are_one_list_that_the_signatures_show(tmp_path):
    """`EvaluationOptions` lists the keyword arguments once: `evaluate` and `prepare` take and
    show (help(), editors) exactly those, and refuse any other as Python does."""
    import inspect

    from mpcpearl_jax.api.evaluate import EvaluationOptions, prepare

    names = list(EvaluationOptions.names())
    evaluate_params = inspect.signature(mpcpearl_jax.evaluate).parameters
    assert list(evaluate_params) == ["run", "on_task_set", *names]
    assert list(inspect.signature(prepare).parameters) == ["run", *names]
    assert evaluate_params["split"].default == "test" == EvaluationOptions().split
    with pytest.raises(TypeError, match=r"^evaluate\(\) got an unexpected keyword argument 'splt'"):
        mpcpearl_jax.evaluate(controller="gp-mpc", splt="val", out=tmp_path / "o")
    with pytest.raises(TypeError, match=r"^prepare\(\) got an unexpected keyword argument 'x'"):
        prepare(controller="gp-mpc", x=1)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "option, value",
    [
        ("episodes", "2"),
        ("seed_index", "0"),
        ("eval_seed", 1.5),
        ("online", "yes"),
        ("overwrite", 1),
        ("tasks", 5),
        ("mpc", "sqp_iters=2"),
        ("eps", "0.5"),
        ("out", 3),
        ("shield", "on"),
    ],
)
def test_a_wrong_type_is_a_type_error_naming_the_option(option, value, tmp_path):
    """An option of the wrong type was a bare comparison error inside the evaluation ('<' not
    supported between 'str' and 'int'), or taken ("yes" as online): a TypeError naming the
    option and what it takes, before anything is loaded or written."""
    from mpcpearl_jax.api.evaluate import EvaluationOptions, prepare

    match = rf"^evaluate\(\): {option} must be .*, not {type(value).__name__} "
    with pytest.raises(TypeError, match=match):
        mpcpearl_jax.evaluate(RUN, **{"tasks": [0], "out": tmp_path / "o", option: value})
    with pytest.raises(TypeError, match=rf"^prepare\(\): {option} must be "):
        prepare(RUN, **{option: value})
    with pytest.raises(TypeError, match=rf"^EvaluationOptions: {option} must be "):
        EvaluationOptions(**{option: value})
    assert not (tmp_path / "o").exists()


def test_the_types_the_callers_pass_are_taken():
    """Task lists as lists, ranges or NumPy arrays, NumPy ints, MPC changes as a list or a
    mapping, paths as strings or Paths."""
    import numpy as np

    from mpcpearl_jax.api.evaluate import prepare

    gp = prepare(controller="gp-mpc", tasks=np.arange(2), mpc={"sqp_iters": 2}, figures="none")
    assert gp.setup.task_ids == [0, 1]
    gp = prepare(controller="gp-mpc", tasks=range(1, 3), mpc=["sqp_iters=2"], eval_seed=np.int64(3))
    assert gp.setup.task_ids == [1, 2]
    policy = prepare(str(RUN), tasks="0-2", episodes=np.int32(1), seed_index=0, shield=True)
    assert policy.setup.task_ids == [0, 1, 2]
