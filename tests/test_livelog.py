"""Live logs: the optional TensorBoard mirror of metrics.jsonl (mpcpearl_jax.training.livelog)."""

import json

import pytest

from mpcpearl_jax.training import livelog

# tensorboardX is an optional extra (`tensorboard`; the `dev` extra includes it)
needs_tensorboardx = pytest.mark.skipif(
    livelog.missing() is not None, reason='tensorboardX not installed: pip install -e ".[dev]"'
)


@needs_tensorboardx
def test_tensorboard_log_holds_the_metrics_rows(tmp_path):
    rows = [
        {"iteration": 1, "train_return": -50.0, "mpc_reasons": {"solved": 3}, "note": "x"},
        {"iteration": 2, "train_return": -20.5, "test_SR": 0.25, "flag": True},
    ]
    with livelog.TensorBoardLog(tmp_path / "tb") as tb:
        for row in rows:
            tb.write(row)
    assert livelog.read_scalars(tmp_path / "tb") == {
        "train_return": [(1, -50.0), (2, -20.5)],
        "mpc_reasons/solved": [(1, 3.0)],
        "test_SR": [(2, 0.25)],
    }


def test_scalars_of_skips_non_numbers():
    row = {"a": 1, "b": float("nan"), "c": True, "d": "s", "e": {"f": 2.5, "g": None}}
    assert livelog.scalars_of(row) == {"a": 1.0, "e/f": 2.5}


def test_a_missing_writer_is_a_clear_error(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_tensorboardx(name, *args, **kwargs):
        if name == "tensorboardX":
            raise ImportError("No module named 'tensorboardX'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_tensorboardx)
    assert "pip install tensorboardX" in livelog.missing()
    with pytest.raises(livelog.LiveLogError, match="tensorboardX"):
        livelog.TensorBoardLog("unused")


class _Trainer:
    """Enough of a Trainer for training.budget.train_for: 1 s per iteration."""

    def __init__(self, clock):
        from mpcpearl_jax.config import preset

        self.cfg = preset("smoke")
        self.num_train, self.horizon, self.clock = 8, 80, clock

    def iteration(self, state):
        self.clock.t += 1.0
        return state + 1, {"iteration": state + 1, "train_return": -10.0 * state}

    def evaluate(self, state, tasks=None, online=False):
        return {"SR": state / 10, "CFR": 1.0, "TT": 80.0, "SPL": 0.0, "MGD": 1.0, "return": -1.0}


@needs_tensorboardx
def test_learning_benchmark_mirrors_its_rows(tmp_path):
    from mpcpearl_jax.training import budget
    from mpcpearl_jax.training.run import Session

    class Clock:
        t = 0.0

        def __call__(self):
            return self.t

    clock = Clock()
    log = tmp_path / "metrics.jsonl"
    with livelog.TensorBoardLog(tmp_path / "tb") as tb:
        trainer = _Trainer(clock)
        budget.train_for(
            Session(trainer.cfg, tmp_path, trainer, 0, tb=tb),
            budget_s=4.0,
            every_s=2.0,
            val_tasks=None,
            clock=clock,
            on_point=None,
        )
    rows = [json.loads(x) for x in log.read_text().splitlines()]
    got = livelog.read_scalars(tmp_path / "tb")
    assert got["train_return"] == [(r["iteration"], r["train_return"]) for r in rows]
    evals = [r for r in rows if "test_SR" in r]
    assert [s for s, _ in got["test_SR"]] == [r["iteration"] for r in evals] == [2, 4]
    assert [v for _, v in got["test_SR"]] == pytest.approx([r["test_SR"] for r in evals])
    assert "iteration" not in got


@pytest.mark.slow
@needs_tensorboardx
def test_training_cli_tensorboard_and_episode_gif(tmp_path):
    """`python -m experiments.restaurant --tensorboard`: every metrics.jsonl number is in the event
    file under its own name; the final evaluation writes episode_test0.gif."""
    from PIL import Image

    from mpcpearl_jax.cli.train import main

    out = tmp_path / "run"
    argv = ["--preset", "smoke", "--eps", "0", "--iterations", "2", "--out", str(out)]
    argv += ["--no-progress", "--tensorboard", "--set", "train.tasks_per_iteration=2"]
    assert main("restaurant", argv) == 0
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    got = livelog.read_scalars(out / livelog.TB_DIR)
    for row in rows:  # event files hold float32 values
        for name, value in livelog.scalars_of(row).items():
            if name != "iteration":
                logged = dict(got[name])[row["iteration"]]
                assert logged == pytest.approx(value, rel=1e-6, abs=1e-6), name
    with Image.open(out / "episode_test0.gif") as im:
        assert im.n_frames == 81
