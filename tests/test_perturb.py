"""Crowd perturbations (envs/perturb.py) against a hand-written NumPy loop, and on the command
line of experiments.evaluate."""

import json
from pathlib import Path

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mpcpearl_jax import make_tasks
from mpcpearl_jax.envs.perturb import (
    Perturbation,
    delay_people,
    parse_perturbation,
    perturb_tasks,
)
from mpcpearl_jax.envs.types import TaskParams

RUN = Path(__file__).resolve().parents[1] / "results" / "restaurant" / "main-default"


def reference(pos: np.ndarray, mask: np.ndarray, delay: int, speed: float):
    """One task, a plain loop over steps and people: re-time by speed, then delay."""
    n, h = pos.shape[:2]
    out_pos = np.zeros_like(pos)
    out_mask = np.zeros_like(mask)
    for t in range(n):
        tau = speed * max(t - delay, 0)
        tau = min(tau, n - 1)
        lo = int(np.floor(tau))
        hi = min(lo + 1, n - 1)
        w = tau - lo
        for k in range(h):
            out_pos[t, k] = (1 - w) * pos[lo, k] + w * pos[hi, k]
            out_mask[t, k] = mask[lo, k] if w < 1e-5 else (mask[lo, k] and mask[hi, k])
    return out_pos, out_mask


def _tasks(n=3, steps=21, people=4, seed=0) -> TaskParams:
    rng = np.random.default_rng(seed)
    pos = np.cumsum(rng.normal(size=(n, steps, people, 2)), axis=1).astype(np.float32)
    mask = rng.uniform(size=(n, steps, people)) > 0.2
    z2 = np.zeros((n, 1, 2), np.float32)
    return TaskParams(
        human_pos=pos,
        human_mask=mask,
        static_lo=z2,
        static_hi=z2,
        static_radius=np.zeros((n, 1), np.float32),
        start=np.zeros((n, 3), np.float32),
        goal=np.ones((n, 2), np.float32),
    )


@settings(max_examples=25, deadline=None)
@given(delay=st.integers(0, 30), speed=st.sampled_from([0.3, 0.5, 0.7, 1.0, 1.3, 2.0, 3.7]))
def test_matches_the_numpy_loop(delay, speed):
    tasks = _tasks()
    got = perturb_tasks(tasks, Perturbation(delay=delay, speed=speed))
    for i in range(3):
        want_pos, want_mask = reference(
            np.asarray(tasks.human_pos[i]), np.asarray(tasks.human_mask[i]), delay, speed
        )
        np.testing.assert_allclose(got.human_pos[i], want_pos, rtol=1e-5, atol=1e-4)
        np.testing.assert_array_equal(got.human_mask[i], want_mask)
    # nothing but the people changes
    for f in ("static_lo", "static_hi", "static_radius", "start", "goal"):
        np.testing.assert_array_equal(getattr(got, f), getattr(tasks, f))


def test_invariants_on_restaurant_tasks():
    tasks = make_tasks("restaurant", "val")
    pos = np.asarray(tasks.human_pos)
    d = perturb_tasks(tasks, Perturbation(delay=12))
    dp = np.asarray(d.human_pos)
    # everyone waits at the start for 12 more steps, then the path goes on unchanged
    np.testing.assert_array_equal(dp[:, :13], np.repeat(pos[:, :1], 13, axis=1))
    np.testing.assert_array_equal(dp[:, 12:], pos[:, : pos.shape[1] - 12])
    fast = np.asarray(perturb_tasks(tasks, Perturbation(speed=2.0)).human_pos)
    np.testing.assert_allclose(fast[:, :41], pos[:, ::2][:, :41], atol=1e-6)
    np.testing.assert_allclose(fast[:, 41:], np.repeat(pos[:, -1:], 40, axis=1), atol=1e-6)
    slow = np.asarray(perturb_tasks(tasks, Perturbation(speed=0.5)).human_pos)
    np.testing.assert_allclose(slow[:, ::2], pos[:, :41], atol=1e-6)
    # the path is never left: a slow person is between two consecutive points of it
    assert perturb_tasks(tasks, Perturbation()) is tasks


def test_single_task_and_jit():
    tasks = _tasks()
    one = jax.tree_util.tree_map(lambda x: x[1], tasks)
    p = Perturbation(delay=2, speed=1.3)
    got = jax.jit(lambda t: perturb_tasks(t, p))(one)
    stacked = perturb_tasks(tasks, p)
    np.testing.assert_allclose(got.human_pos, stacked.human_pos[1], atol=1e-6)


def delay_reference(pos: np.ndarray, mask: np.ndarray, delays: np.ndarray):
    """One task, a plain loop: person k stands at its step-0 entry for delays[k] more steps."""
    out_pos, out_mask = np.zeros_like(pos), np.zeros_like(mask)
    for t in range(pos.shape[0]):
        for k in range(pos.shape[1]):
            src = max(t - int(delays[k]), 0)
            out_pos[t, k], out_mask[t, k] = pos[src, k], mask[src, k]
    return out_pos, out_mask


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), top=st.integers(0, 40))
def test_per_person_delays_match_the_numpy_loop(seed, top):
    tasks = _tasks(seed=seed % 7)
    delays = np.random.default_rng(seed).integers(0, top + 1, size=(3, 4))
    got = jax.jit(delay_people)(tasks, delays)
    for i in range(3):
        want_pos, want_mask = delay_reference(
            np.asarray(tasks.human_pos[i]), np.asarray(tasks.human_mask[i]), delays[i]
        )
        np.testing.assert_array_equal(got.human_pos[i], want_pos)
        np.testing.assert_array_equal(got.human_mask[i], want_mask)
    for f in ("static_lo", "static_hi", "static_radius", "start", "goal"):
        np.testing.assert_array_equal(getattr(got, f), getattr(tasks, f))
    # one delay for everyone is the evaluation's delay=K; a single task works unstacked
    k = int(delays[0, 0])
    same = delay_people(tasks, np.full((3, 4), k))
    want = perturb_tasks(tasks, Perturbation(delay=k))
    np.testing.assert_array_equal(same.human_pos, want.human_pos)
    one = delay_people(jax.tree_util.tree_map(lambda x: x[2], tasks), delays[2])
    np.testing.assert_array_equal(one.human_pos, got.human_pos[2])


def test_parse_and_bad_values():
    assert parse_perturbation("none") == Perturbation()
    assert parse_perturbation("delay=6") == Perturbation(delay=6)
    assert parse_perturbation(" speed=1.3, delay=3 ") == Perturbation(delay=3, speed=1.3)
    assert parse_perturbation("delay=3,speed=1.3").label == "delay=3,speed=1.3"
    for bad, want in (
        ("delay=-1", "delay"),
        ("delay=1.5", "int"),
        ("speed=0", "speed"),
        ("speed=fast", "number"),
        ("wobble=2", "expected delay=K"),
        ("delay=1,delay=2", "twice"),
    ):
        with pytest.raises(ValueError, match=want):
            parse_perturbation(bad)


@pytest.mark.slow  # the command line of --perturb (~13 s); perturb_tasks is tested fast
def test_evaluate_cli_perturb(tmp_path, capsys):
    from mpcpearl_jax.cli import evaluate

    base = [str(RUN), "--split", "val", "--tasks", "0-3", "--figures", "none"]
    assert evaluate.main([*base, "--out", str(tmp_path / "a")]) == 0
    assert evaluate.main([*base, "--perturb", "delay=12", "--out", str(tmp_path / "b")]) == 0
    a = json.loads((tmp_path / "a" / "results.json").read_text())
    b = json.loads((tmp_path / "b" / "results.json").read_text())
    assert a["perturbation"] == "none" and b["perturbation"] == "delay=12"
    assert a["per_task"]["return"] != b["per_task"]["return"]  # the crowd really changed
    assert "crowd perturbed delay=12" in capsys.readouterr().out
    assert evaluate.main([*base, "--perturb", "delay=-3"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "delay" in err and "\n" not in err
    # the default folder names the perturbation
    argv = ["--controller", "gp-mpc", "--split", "test", "--tasks", "0", "--figures", "none"]
    s = evaluate.setup(evaluate.make_parser().parse_args([*argv, "--perturb", "speed=0.7"]))
    assert s.out.name == "gp-mpc-restaurant-test-speed0.7"
