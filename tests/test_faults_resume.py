"""Fault injection on a training run: kill -9 at any moment then --resume (ends identical to
a run never stopped), Ctrl-C, a corrupt newest checkpoint, torn metrics lines, a full disk while
saving, and --resume refused below the finished count or with nothing to resume.

The runs are `faults_helpers`' smoke run shrunk to a few seconds; the long variant (the real
command line, kill points at random moments, eps 0 and 0.2) is marked slow.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from faults_helpers import (
    ITERATIONS,
    _interrupted_at,
    _one_line_error,
    _sigint_when,
    assert_same_run,
    kill_when,
    rows_at_least,
    small_args,
    small_cfg,
    spawn,
    train_only,
    writing_checkpoint,
)

from mpcpearl_jax.cli.train import main
from mpcpearl_jax.runfolder import LOG_FILE, read_log
from mpcpearl_jax.training.checkpoint import CheckpointError
from mpcpearl_jax.training.run import open_session
from mpcpearl_jax.training.trainer import IterationAbandoned, Trainer


@pytest.mark.slow
@pytest.mark.parametrize("eps", [0.0, 0.2])
def test_kill9_at_random_points_of_the_command_line(tmp_path, eps):
    """The real command line (training, then the final evaluation) killed with SIGKILL six times,
    each time resumed with --resume: at a random moment of start-up, during a checkpoint write,
    at three random moments of training (a random iteration, then a random delay into it) and
    during the final evaluation. It ends identical to a run never stopped (checkpoint, policy,
    metrics and results.json)."""
    iterations = 12
    ref, run = tmp_path / "ref", tmp_path / "run"
    proc = spawn(small_args(eps, ref, iterations), tmp_path / "ref.txt", cli=True)
    assert proc.wait(timeout=600) == 0, (tmp_path / "ref.txt").read_text()[-3000:]
    args = small_args(eps, run, iterations)
    rng = random.Random(1234 + int(10 * eps))
    rows = sorted(rng.sample(range(3, iterations - 1, 2), 3))  # 2 apart: each one still ahead
    clock = {}

    def after(n: int, delay: float):
        def cond(log) -> bool:
            if rows_at_least(run, n)():
                clock.setdefault(n, time.monotonic())
                return time.monotonic() - clock[n] >= delay
            return False

        return cond

    t_start = rng.uniform(1.0, 6.0)
    points = [
        (f"start-up, {t_start:.1f} s", lambda log: time.monotonic() - started >= t_start),
        ("checkpoint write", lambda log: writing_checkpoint(run, min_step=2)()),
        *[
            (f"iteration {n + 1}, +{d:.2f} s", after(n, d))
            for n, d in ((n, rng.uniform(0.0, 0.3)) for n in rows)
        ],  # fmt: skip
        ("final evaluation", lambda log: "evaluating" in log.read_text()),
    ]
    report = []
    for i, (name, cond) in enumerate(points):
        log = tmp_path / f"victim{i}.txt"
        log.touch()
        started = time.monotonic()
        proc = spawn([*args, "--resume"] if (run / "config.json").exists() else args, log, cli=True)
        killed = kill_when(proc, lambda cond=cond, log=log: cond(log), timeout=600)
        report.append((name, killed))
        if not killed:  # it finished first: nothing left to interrupt
            assert proc.returncode == 0, log.read_text()[-3000:]
            break
    if report[-1][1]:
        log = tmp_path / "last.txt"
        proc = spawn([*args, "--resume"], log, cli=True)
        assert proc.wait(timeout=600) == 0, log.read_text()[-3000:]
    print(f"eps {eps}: kill points {report}")
    assert sum(k for _, k in report) >= 5, report
    assert_same_run(ref, run)
    res = [json.loads((d / "results.json").read_text()) for d in (ref, run)]
    machines = [r.pop("machine") for r in res]  # the load average differs between the two
    assert all(m["cpu_count"] >= 1 for m in machines)
    assert res[0] == res[1]
    assert (run / "learning_curves.png").is_file()


@pytest.mark.slow  # Ctrl-C, then SIGKILL inside a checkpoint write (~45 s)
def test_ctrl_c_then_kill9_in_a_checkpoint_write_then_resume_is_exact(tmp_path, ref0):
    """The command line stopped by Ctrl-C (exit 130, the iteration saved, one line), resumed and
    killed with SIGKILL while a checkpoint is being written, resumed again: the run ends
    identical to one never stopped."""
    run, log = tmp_path / "run", tmp_path / "log.txt"
    args = small_args(0.0, run)
    proc = spawn(args, log, cli=True)
    t_sig = _sigint_when(proc, rows_at_least(run, 2))
    assert proc.wait(timeout=60) == 130
    assert time.monotonic() - t_sig < 10
    text = log.read_text()
    n = _interrupted_at(text)
    assert 2 <= n < ITERATIONS - 1 and (run / "checkpoints" / str(n)).is_dir()
    assert "Traceback" not in text and len(read_log(run / LOG_FILE)) == n
    proc = spawn([*args, "--resume"], log)
    assert kill_when(proc, writing_checkpoint(run, min_step=n + 1))
    assert any("tmp" in p.name for p in (run / "checkpoints").iterdir())  # killed mid-write
    assert spawn([*args, "--resume"], log).wait(timeout=240) == 0, log.read_text()[-3000:]
    assert not any("tmp" in p.name for p in (run / "checkpoints").iterdir())
    assert_same_run(ref0, run)


@pytest.mark.slow  # (~19 s)
def test_update_chunks_give_one_scan_and_answer_stop():
    """The update phase in chunks of 2 + 1 steps equals one scan of its 3 steps (same keys, bit
    for bit), and a stop request is answered between chunks."""
    tr = Trainer(small_cfg(0.0))  # 3 gradient steps per iteration
    state, _ = tr.initial_collection(tr.init_state())
    copy = jax.tree_util.tree_map(jnp.copy, state)
    one = tr.update_phase(state, None)  # chunk 25: one scan
    tr.update_chunk = 2
    chunked = tr.update_phase(copy, None)
    leaves = jax.tree_util.tree_leaves
    for x, y in zip(leaves(one), leaves(chunked), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    calls = []

    def stop() -> bool:
        calls.append(1)
        return len(calls) > 1

    with pytest.raises(IterationAbandoned):
        tr.update_phase(chunked[0], stop)
    assert len(calls) == 2  # one chunk ran, the second was not started


# orbax leaves an unraisable warning behind when it fails to read the garbled checkpoint
@pytest.mark.slow  # (~26 s)
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_corrupt_newest_checkpoint_and_torn_log_line_fall_back_and_resume_exactly(
    tmp_path, ref0, capsys
):
    run = tmp_path / "run"
    shutil.copytree(ref0, run)
    last = run / "checkpoints" / str(ITERATIONS)
    for p in last.rglob("*"):
        if p.is_file() and p.stat().st_size > 0 and "metadata" not in p.name.lower():
            p.write_bytes(b"garbage")
    with open(run / LOG_FILE, "ab") as f:
        f.write(b'{"iteration": 7, "train_ret')  # a line cut by a crash
    capsys.readouterr()
    train_only(small_cfg(0.0), run, resume=True)
    err = capsys.readouterr().err
    assert f"checkpoints/{ITERATIONS}: cannot restore" in err
    assert f"falling back to iteration {ITERATIONS - 1}" in err
    assert f"{run / LOG_FILE}: dropped a torn last line" in err
    # orbax's multi-line error (~60 lines of TensorStore spec) is cut to its first line
    assert len(err.strip().splitlines()) == 2, err
    assert (run / "corrupt_checkpoints" / str(ITERATIONS)).is_dir()
    assert_same_run(ref0, run)  # iteration 6 redone from 5: the same


def test_torn_line_in_the_middle_of_the_log_is_an_error(tmp_path):
    path = tmp_path / LOG_FILE
    path.write_text('{"iteration": 1}\n{"iteration": 2, "x\n{"iteration": 3}\n')
    with pytest.raises(CheckpointError, match="line 2"):
        read_log(path)


def test_resume_below_the_finished_count_is_refused(ref0, capsys):
    before = (ref0 / "config.json").read_bytes()
    with pytest.raises(CheckpointError, match=f"finished {ITERATIONS} iterations; --iterations 3"):
        open_session(small_cfg(0.0, 3), ref0, resume=True)
    assert main("restaurant", small_args(0.0, ref0, 3, "--resume")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--iterations 3 is below" in err[0]
    assert (ref0 / "config.json").read_bytes() == before  # untouched by a refused command


def test_resume_with_nothing_to_resume_is_an_error(tmp_path, ref0, capsys):
    """--resume on a folder whose log holds iterations but no checkpoint: one line naming the
    folder, and metrics.jsonl untouched; with nothing logged either it says so and starts at 0."""
    run = tmp_path / "run"
    shutil.copytree(ref0, run)
    shutil.rmtree(run / "checkpoints")
    before = (run / LOG_FILE).read_bytes()
    line = _one_line_error(capsys, small_args(0.0, run, ITERATIONS, "--resume"))
    assert f"{run}: nothing to resume: no checkpoint" in line and "logs 6 iteration(s)" in line
    assert (run / LOG_FILE).read_bytes() == before
    (run / LOG_FILE).write_text("")
    with open_session(small_cfg(0.0), run, resume=True) as sess:
        pass
    assert sess.done == 0 and "starting at iteration 0" in capsys.readouterr().err


def test_full_disk_while_saving_is_one_line_and_the_run_resumes_exactly(
    tmp_path, ref0, monkeypatch, capsys
):
    """ENOSPC injected into the checkpoint write of iteration 3 (orbax's own error, after a
    partial temporary folder), then into metrics.jsonl on the resumed run: each time exit 2 with
    one line naming the path, the cause and the iteration a resume starts from, no temporary
    folder left; the run then resumes to the same end as a run never stopped."""
    import errno

    import orbax.checkpoint as ocp

    run = tmp_path / "run"
    real_save, real_write = ocp.CheckpointManager.save, os.write

    def full_disk_at_3(self, step, *a, **k):
        if step == 3:
            part = run / "checkpoints" / "3.orbax-checkpoint-tmp-1" / "default"
            part.mkdir(parents=True)
            (part / "d").write_bytes(b"partial")
            raise ValueError(
                f'RESOURCE_EXHAUSTED: Error writing local file "{part}/_sharding": Failed to write '
                "17259 bytes to file 4: No space left on device [os_error_code='28']"
            )
        return real_save(self, step, *a, **k)

    monkeypatch.setattr(ocp.CheckpointManager, "save", full_disk_at_3)
    line = _one_line_error(capsys, small_args(0.0, run))
    assert line == (
        f"error: {run / 'checkpoints' / '3'}: cannot save (No space left on device); --resume "
        "continues from iteration 2 once the cause is fixed"
    )
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["1", "2"]
    monkeypatch.setattr(ocp.CheckpointManager, "save", real_save)

    def full_log_at_5(fd, data):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            target = ""
        if target.endswith(LOG_FILE) and b'"iteration": 5' in bytes(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", full_log_at_5)
    line = _one_line_error(capsys, small_args(0.0, run, ITERATIONS, "--resume"))
    assert line == (
        f"error: {run / LOG_FILE}: cannot write (No space left on device); --resume continues "
        "from iteration 4 once the cause is fixed"
    )
    monkeypatch.setattr(os, "write", real_write)
    assert not any("tmp" in p.name for p in (run / "checkpoints").iterdir())
    train_only(small_cfg(0.0), run, resume=True)
    assert_same_run(ref0, run)
