"""The pipelined iteration (`train.pipeline`): the episodes of iteration k + 1 are collected
beside the gradient steps of iteration k, by the policy and encoder from before those steps;
runs stopped and resumed end identical to runs never stopped; the option is refused where it
cannot apply."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from faults_helpers import (
    ROOT,
    _env,
    _interrupted_at,
    assert_same_run,
    final_checkpoint,
    metric_rows,
    rows_at_least,
    signal_group_when,
    small_args,
    small_cfg,
    spawn,
    train_only,
)

from mpcpearl_jax.runfolder import LOG_FILE, read_log
from mpcpearl_jax.training.protocol import split_keys
from mpcpearl_jax.training.trainer import Trainer

PIPE = ("--set", "train.pipeline=true")


def pipelined_cfg(eps: float, iterations: int):
    cfg = small_cfg(eps, iterations)
    return cfg.replace(train=dataclasses.replace(cfg.train, pipeline=True))


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def test_pipelined_collection_acts_with_the_parameters_from_before_the_updates():
    """Iteration 2 of a pipelined run stores exactly the episodes that the policy and encoder of
    the end of iteration 1 collect (not those after iteration 2's updates, which differ), and its
    learner is what the gradient steps make of iteration 1's state; run twice from the same state
    it gives the same values (the two threads never change what is computed)."""
    tr = Trainer(pipelined_cfg(0.2, 2))
    s1, _ = tr.iteration(tr.init_state())
    copy = lambda s: jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), s)  # noqa: E731
    ref = copy(s1)
    s2, log = tr.iteration(copy(s1))
    assert log["iteration"] == 2 and log["update_s"] > 0 and log["collect_s"] > 0
    again, _ = tr.iteration(copy(s1))
    for a, b in zip(_leaves(s2), _leaves(again), strict=True):
        np.testing.assert_array_equal(a, b)

    # the reference, in one thread: the collection's keys, then the episodes of the parameters
    # before the updates stored behind the updates' buffers
    keys, sub = split_keys(ref.key, 1)
    from mpcpearl_jax.training.trainer import TrainState

    def ahead(params):
        acting = {"policy": params["policy"], "encoder": params["encoder"]}
        side = TrainState(None, None, ref.enc, ref.tasks, sub[:, 0], ref.iteration)
        return tr._collect_ahead(side, acting, 3)

    enc, tasks, ids, per_task, _, _ = ahead(ref.learner.params)
    expected_rl = tr._store(ref.rl, ids, per_task)
    for a, b in zip(_leaves(expected_rl), _leaves(s2.rl), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(_leaves(enc), _leaves(s2.enc), strict=True):
        np.testing.assert_array_equal(a, b)
    updated, _ = tr.update_phase(ref.replace(key=keys))
    for a, b in zip(_leaves(updated.learner), _leaves(s2.learner), strict=True):
        np.testing.assert_array_equal(a, b)
    # the check can fail: the parameters after the updates collect other episodes
    _, _, _, other, _, _ = ahead(s2.learner.params)
    assert any(
        not np.array_equal(a, b)
        for a, b in zip(_leaves(other[0].action), _leaves(per_task[0].action), strict=True)
    )


def test_a_pipelined_run_trained_in_two_parts_equals_one_run(tmp_path):
    """Two pipelined iterations, then the same run resumed to four, end bit for bit where four
    iterations in one process end (checkpoint, policy and metrics), with MPC infusion."""
    ref, run = tmp_path / "ref", tmp_path / "run"
    train_only(pipelined_cfg(0.2, 4), ref)
    train_only(pipelined_cfg(0.2, 2), run)
    train_only(pipelined_cfg(0.2, 4), run, resume=True)
    # the first part's end evaluated its policy (fields test_*); the rest is the same
    no_eval = lambda rows: [{k: v for k, v in r.items() if not k.startswith("test_")} for r in rows]  # noqa: E731
    assert no_eval(metric_rows(ref)) == no_eval(metric_rows(run))
    for a, b in zip(_leaves(final_checkpoint(ref)), _leaves(final_checkpoint(run)), strict=True):
        np.testing.assert_array_equal(a, b)
    assert (ref / "policy.msgpack").read_bytes() == (run / "policy.msgpack").read_bytes()
    rows = read_log(run / LOG_FILE)
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4]
    assert all(r["mpc_rows"] > 0 for r in rows)  # the MPC acted in the collections beside steps


@pytest.mark.slow  # three small trainings in subprocesses (~60 s)
@pytest.mark.skipif(not hasattr(os, "killpg"), reason="POSIX process groups")
def test_ctrl_c_to_the_process_group_during_a_pipelined_iteration_saves_and_resumes_exactly(
    tmp_path,
):
    """A pipelined run with MPC infusion (eps 0.5) and two MPC pool workers gets SIGINT to its
    whole process group after its second iteration, while the next iteration's collection and
    updates run: exit 130, one line, the finished iteration saved; resumed to one more iteration
    it ends identical to a run never stopped."""
    run, ref, log = tmp_path / "run", tmp_path / "ref", tmp_path / "log.txt"
    extra = (*PIPE, "--set", "mpc.n_workers=2", "--set", "train.checkpoint_interval=50")
    proc = spawn(small_args(0.5, run, 40, *extra), log, cli=True, start_new_session=True)
    # 0.05 s into the third iteration
    rc = signal_group_when(proc, rows_at_least(run, 2), signal.SIGINT, log, after_s=0.05)
    text = log.read_text()
    assert rc == 130, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    n = _interrupted_at(text)
    assert n >= 2 and (run / "checkpoints" / str(n)).is_dir(), text[-3000:]
    resumed = spawn([*small_args(0.5, run, n + 1, *extra), "--resume"], log)
    assert resumed.wait(timeout=240) == 0, log.read_text()[-3000:]
    straight = spawn(small_args(0.5, ref, n + 1, *extra), tmp_path / "ref.txt")
    assert straight.wait(timeout=240) == 0, (tmp_path / "ref.txt").read_text()[-3000:]
    assert_same_run(ref, run)


def test_pipeline_on_grbal_is_refused_in_one_line(tmp_path):
    """GrBAL trains no PEARL iteration: `train.pipeline` there is a one-line error."""
    cmd = [sys.executable, "-m", "experiments.grbal", "--preset", "smoke", *PIPE]
    proc = subprocess.run(
        [*cmd, "--out", str(tmp_path / "g")],
        cwd=ROOT,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stdout + proc.stderr
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and "train.pipeline" in err[0], proc.stderr
    assert not (tmp_path / "g").exists()
