"""A stop (Ctrl-C, SIGTERM, SIGHUP: KeyboardInterrupt in the command) during the final
evaluation's figures: the episode GIF is written under a temporary name and renamed once whole
(a stop part-way leaves the previous GIF or none, never a short one that looks complete), and
results.json, which marks a run finished for --resume, is written after every figure, so that
--resume runs the final evaluation again as the command's line says."""

from __future__ import annotations

import signal
import types

import jax
import numpy as np
import pytest
from PIL import Image

from mpcpearl_jax.config import preset
from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.evaluation import animate
from mpcpearl_jax.training import final


def _frames(path) -> int:
    with Image.open(path) as im:
        return im.n_frames


def test_a_gif_stopped_part_way_leaves_the_previous_one_whole(tmp_path, monkeypatch):
    env = make_env("restaurant")
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test", 0))
    horizon = env.config.horizon
    start, goal = np.asarray(task.start)[:2], np.asarray(task.goal)
    pos = start + np.linspace(0.0, 1.0, horizon + 1)[:, None] * (goal - start)
    path = tmp_path / "episode_test0.gif"
    animate.animate_episode(path, task, env.config, pos)
    assert _frames(path) == horizon + 1
    before = path.read_bytes()
    figure = animate._figure

    def stopped_at_frame_30(*args):
        fig, draw = figure(*args)

        def draw_until(i):
            if i == 30:
                raise KeyboardInterrupt  # a stop signal, as the commands turn it
            return draw(i)

        return fig, draw_until

    monkeypatch.setattr(animate, "_figure", stopped_at_frame_30)
    with pytest.raises(KeyboardInterrupt):
        animate.animate_episode(path, task, env.config, pos[::-1])
    assert path.read_bytes() == before  # the previous GIF, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary left
    path.unlink()
    with pytest.raises(KeyboardInterrupt):
        animate.animate_episode(path, task, env.config, pos)
    assert not any(tmp_path.iterdir())  # none rather than a short one


def _stop_part_way(monkeypatch) -> None:
    """Every matplotlib savefig writes half its file, then stops (a stop signal while the PNG
    is being written, as the commands turn it; or a disk that fills up)."""
    from matplotlib.figure import Figure

    savefig = Figure.savefig

    def stopped(self, fname, *args, **kwargs):
        savefig(self, fname, *args, **kwargs)
        data = open(fname, "rb").read()
        with open(fname, "wb") as f:
            f.write(data[: len(data) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", stopped)


def test_a_png_stopped_part_way_leaves_the_previous_one_whole(tmp_path, monkeypatch):
    """The final evaluation's PNG figures (learning_curves.png, trajectory_test0.png, a time
    budget's curve.png), as its GIF: written under a temporary name and renamed once whole. A
    stop part-way left a cut-short PNG under the figure's name (the previous one lost)."""
    from mpcpearl_jax.envs import save_trajectory
    from mpcpearl_jax.evaluation.report import plot_learning_curves
    from mpcpearl_jax.training.budget import plot_curve

    env = make_env("restaurant")
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test", 0))
    start, goal = np.asarray(task.start)[:2], np.asarray(task.goal)
    pos = start + np.linspace(0.0, 1.0, env.config.horizon + 1)[:, None] * (goal - start)
    row = {"iteration": 1, "train_return": -1.0, "test_return": -2.0, "test_SR": 0.5, "test_CFR": 0}
    point = {f"{s}_{m}": 0.5 for s in ("test", "val") for m in ("SR", "CFR", "return")}
    figures = {
        "trajectory_test0.png": lambda p: save_trajectory(
            "restaurant", p, task, {"policy": (pos, None)}, env.config
        ),
        "learning_curves.png": lambda p: plot_learning_curves([("x", [row, row])], p),
        "curve.png": lambda p: plot_curve([{**point, "minutes": 1.0, "grad_steps": 10}], p, "x"),
    }
    for name, draw in figures.items():
        path = tmp_path / name
        draw(path)
        before = path.read_bytes()
        assert before.startswith(b"\x89PNG")
        with monkeypatch.context() as m:
            _stop_part_way(m)
            with pytest.raises(KeyboardInterrupt):
                draw(path)
        assert path.read_bytes() == before, name  # the previous figure, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(figures)  # no temporary left


class _Trainer:
    """What `final_evaluation` reads of a trainer, with fixed results."""

    def __init__(self):
        self.cfg = preset("smoke")
        self.env = types.SimpleNamespace(config=None)

    def evaluate_episodes(self, state):
        return {"SR": 1.0}, {}

    def evaluate(self, state, online=False, tasks=None):
        return {"SR": 1.0}


@pytest.fixture
def figures(monkeypatch):
    """final_evaluation's figures replaced by a record of the files they would write."""
    import mpcpearl_jax.envs as envs

    made = []
    monkeypatch.setattr(envs, "tasks_for", lambda *a, **k: (_ for _ in ()).throw(ValueError("x")))
    monkeypatch.setattr(final, "machine_info", lambda: {})
    monkeypatch.setattr(final, "plot_learning_curves", lambda runs, path, **k: made.append(path))
    monkeypatch.setattr(final, "_trajectory_figure", lambda t, raw, d: made.append("trajectory"))
    monkeypatch.setattr(final, "_episode_gif", lambda t, raw, d, label: made.append("gif"))
    return made


def test_results_json_is_written_after_every_figure(tmp_path, monkeypatch, figures):
    (tmp_path / "metrics.jsonl").write_text("")

    def stopped(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(final, "_episode_gif", stopped)
    with pytest.raises(KeyboardInterrupt):
        final.final_evaluation(_Trainer(), None, tmp_path, "x")
    assert not (tmp_path / "results.json").exists()  # --resume evaluates again


def test_a_finished_final_evaluation_writes_results_json(tmp_path, figures):
    (tmp_path / "metrics.jsonl").write_text("")
    results = final.final_evaluation(_Trainer(), None, tmp_path, "x")
    assert figures[1:] == ["trajectory", "gif"] and (tmp_path / "results.json").is_file()
    assert results["test_adapt"] == {"SR": 1.0}


# a small training (2 iterations) and two final evaluations through the command line: 241 s
# on the loaded 2-core CPU; the fast siblings are the three tests above
@pytest.mark.slow
@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX process groups")
def test_a_hangup_in_the_final_evaluation_then_resume_finishes_it(tmp_path):
    """SIGHUP to the command's process group once its first figure is written: exit 129, one
    line saying --resume runs the final evaluation, no results.json and no part of a GIF; the
    same command with --resume evaluates it: results.json and the GIF with every frame."""
    from faults_helpers import signal_group_when, small_args, spawn

    run, log = tmp_path / "run", tmp_path / "log.txt"
    proc = spawn(small_args(0.0, run, 2), log, cli=True, start_new_session=True)
    rc = signal_group_when(proc, (run / "learning_curves.png").exists, signal.SIGHUP, log)
    text = log.read_text()
    assert rc == 128 + signal.SIGHUP, text[-3000:]
    assert "Traceback" not in text and "--resume runs the final evaluation" in text, text[-3000:]
    assert not (run / "results.json").exists() and not (run / "episode_test0.gif").exists()
    assert not list(run.glob(".*tmp*")), sorted(p.name for p in run.iterdir())
    resumed = spawn([*small_args(0.0, run, 2), "--resume"], log, cli=True)
    assert resumed.wait(timeout=900) == 0, log.read_text()[-3000:]
    assert "all 2 iteration(s) trained before; evaluating" in log.read_text()
    assert (run / "results.json").is_file() and _frames(run / "episode_test0.gif") == 81
