"""Stopping a training the ways a user stops it: Ctrl-C in a terminal (SIGINT to the whole process
group, MPC pool workers included), SIGTERM (to the group, as `kill -TERM -PGID` or a scheduler
sends it) and SIGHUP: exit 128 + the signal, one line `interrupted at iteration N; continue with
--resume`, no traceback, a checkpoint of the iteration it stopped at (before the first scheduled
one too), the MPC workers gone, and `--resume` continuing the run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from faults_helpers import ROOT, _env, _interrupted_at, rows_at_least, small_args, spawn

from mpcpearl_jax.runfolder import LOG_FILE, read_log
from mpcpearl_jax.training.loop import Progress, train_loop
from mpcpearl_jax.training.trainer import IterationAbandoned


def _children(pid: int) -> list[int]:
    """The live processes whose parent is `pid` (from /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # state, ppid, ...
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(entry.name))
    return found


def _mpc_workers(pid: int) -> list[int]:
    """The spawned pool workers among `pid`'s children (their command line runs spawn_main)."""
    workers = []
    for child in _children(pid):
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmd:
            workers.append(child)
    return workers


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


# two trainings (the stopped run and its resume) with MPC infusion: ~40 s each on a quiet 2-core
# CPU; the fast set keeps the pool-worker test below, which runs the same pool setup
@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_to_the_whole_process_group_saves_and_resumes(tmp_path, sig):
    """The command line with MPC infusion (eps 0.5) and two MPC pool workers, in a process group
    of its own as a terminal starts it, gets the signal sent to the whole group after its second
    iteration (before its first scheduled checkpoint, every 50 iterations): exit 128 + the signal,
    one `interrupted at iteration N` line, no traceback, a checkpoint at N, the workers gone; the
    same command with --resume continues from N."""
    run, log = tmp_path / "run", tmp_path / "log.txt"
    extra = ("--set", "mpc.n_workers=2", "--set", "train.checkpoint_interval=50")
    args = small_args(0.5, run, 40, *extra)
    proc = spawn(args, log, cli=True, start_new_session=True)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 240
        while not (rows_at_least(run, 2)() and len(workers := _mpc_workers(proc.pid)) >= 2):
            assert proc.poll() is None, log.read_text()[-3000:]
            assert time.monotonic() < deadline, "no MPC workers after two iterations"
            time.sleep(0.05)
        os.killpg(proc.pid, sig)  # what Ctrl-C in a terminal does (SIGINT to the group)
        rc = proc.wait(timeout=90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = log.read_text()
    assert rc == 128 + sig, text[-3000:]
    assert "Traceback" not in text and "BrokenProcessPool" not in text, text[-3000:]
    n = _interrupted_at(text)
    assert n >= 2 and (run / "checkpoints" / str(n)).is_dir(), text[-3000:]
    assert len(read_log(run / LOG_FILE)) == n
    deadline = time.monotonic() + 10
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(w) for w in workers), "MPC workers outlived the run"
    # the same command continued (train only: the final evaluation is not what is tested here)
    resumed = spawn([*small_args(0.5, run, n + 1, *extra), "--resume"], log)
    assert resumed.wait(timeout=240) == 0, log.read_text()[-3000:]
    assert [r["iteration"] for r in read_log(run / LOG_FILE)] == list(range(1, n + 2))
    assert (run / "checkpoints" / str(n + 1)).is_dir()


_POOL_PARENT = """
import os, signal, sys, time
from multiprocessing import resource_tracker
from mpcpearl_jax.mpc.bridge import _stop_signals_blocked, make_pool

if __name__ == "__main__":
    got = []
    signal.signal(signal.SIGINT, lambda s, f: got.append(s))
    signal.signal(signal.SIGHUP, lambda s, f: got.append(s))
    pool = make_pool(2)
    with _stop_signals_blocked():
        first = list(pool.map(time.sleep, [0.5, 0.5]))
    groups = set(pool.map(os.getpgid, [0, 0]))
    tracker = resource_tracker._resource_tracker._pid
    print("ready", flush=True)
    while len(got) < 2:
        time.sleep(0.01)
    time.sleep(0.5)
    alive = os.waitpid(tracker, os.WNOHANG) == (0, 0)
    print(os.getpgid(0) in groups, alive, sorted(pool.map(abs, [-1, -2, -3, -4])), got, flush=True)
    pool.shutdown()
"""


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="POSIX signals")
def test_mpc_pool_workers_survive_ctrl_c_and_hangup_to_the_process_group(tmp_path):
    """Ctrl-C and a closed terminal (SIGINT, SIGHUP to the whole process group) reach the training
    process only: the pool's workers (`pool_worker_init`) are in a group of their own and ignore
    both, and multiprocessing's resource tracker survives them (`make_pool`), so the pool still
    works and the training process can save and shut it down without a traceback."""
    script = tmp_path / "parent.py"
    script.write_text(_POOL_PARENT)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    proc = subprocess.Popen(
        [sys.executable, str(script)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env=env,
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        os.killpg(proc.pid, signal.SIGINT)
        time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGHUP)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    # the workers in their own group, multiprocessing's resource tracker alive, the pool working
    assert out.strip() == f"False True [1, 2, 3, 4] {[int(signal.SIGINT), int(signal.SIGHUP)]}", err
    assert "Traceback" not in err, err


class _Trainer:
    """One iteration = +1; `stop()` is polled inside the iteration it is given to."""

    def __init__(self, flag: dict, stop_in: int):
        self.flag, self.stop_in, self.polled = flag, stop_in, []

    def iteration(self, state, stop=None):
        it = state + 1
        if it == self.stop_in:
            self.flag["stop"] = True  # the signal arrives during this iteration
        if stop is not None and stop():
            self.polled.append(it)
            raise IterationAbandoned
        return it, {"iteration": it}


@pytest.mark.parametrize("interval,stop_in,saved", [(50, 3, 3), (1, 3, 2), (50, 1, None)])
def test_a_stop_inside_an_iteration_finishes_it_when_abandoning_would_lose_work(
    interval, stop_in, saved
):
    """A stop inside iteration k: with iteration k - 1 unsaved (no checkpoint yet) the loop
    finishes k, saves it and stops; with k - 1 saved (a checkpoint every iteration), or in the
    first iteration, it abandons k at once (nothing is lost)."""
    flag = {"stop": False}
    trainer, saves = _Trainer(flag, stop_in), []
    p = Progress()
    kw = dict(
        until=lambda p: p.iterations >= 10,
        save=lambda it, s: saves.append(it),
        on_row=lambda row, state, p: None,
        log=lambda row: None,
        checkpoint_after=lambda p, _: p.iterations % interval == 0,
        stop=lambda: flag["stop"],
    )
    if saved is None:  # the first iteration: abandoned, nothing to save (resume starts at 0)
        with pytest.raises(IterationAbandoned):
            train_loop(trainer, 0, p, **kw)
        assert p.saved == -1 and p.iterations == 0 and saves == []
        return
    if interval == 1:
        with pytest.raises(IterationAbandoned):
            train_loop(trainer, 0, p, **kw)
        assert trainer.polled == [stop_in] and p.saved == saved == p.iterations
        return
    state = train_loop(trainer, 0, p, **kw)
    assert p.stopped == "interrupted" and state == saved and saves == [saved]
    assert trainer.polled == []


def _stopped_after(cmd, delay, sig, log, env, after=None):
    """Run `cmd` in a process group of its own, send `sig` to the group `delay` seconds after it
    started (with `after`: after its output first holds that text; it must still run), wait;
    -> (exit code, its output)."""
    with open(log, "w") as f:
        proc = subprocess.Popen(
            cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
        t_end = time.monotonic() + 120
        while after is not None and after not in log.read_text():
            assert proc.poll() is None and time.monotonic() < t_end, log.read_text()[-2000:]
            time.sleep(0.05)
        time.sleep(delay)
        assert proc.poll() is None, log.read_text()[-2000:]
        os.killpg(proc.pid, sig)
        rc = proc.wait(timeout=120)
    return rc, log.read_text()


def _no_crash(text):
    assert "Traceback" not in text and "Fatal Python error" not in text, text[-2000:]


@pytest.mark.slow  # (~90 s: eight start-ups)
@pytest.mark.skipif(not hasattr(os, "killpg"), reason="POSIX process groups")
def test_ctrl_c_during_start_up_is_one_line_and_exit_130_wherever_it_lands(tmp_path):
    """Ctrl-C (SIGINT to the process group) at eight moments of a training's start-up, a cold
    compilation cache so that the first programs really compile: a signal that landed inside
    XLA's compiler used to crash the process at exit (SIGSEGV after the line "interrupted before
    training started"). Wherever it lands: exit 130, one line, no traceback, no crash."""
    env = {**_env(), "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "cache")}
    cmd = [sys.executable, "-m", "experiments.restaurant", "--preset", "smoke"]
    cmd += ["--iterations", "50", "--no-progress"]
    for i, delay in enumerate((3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0)):
        out = ["--out", str(tmp_path / f"r{i}")]
        rc, text = _stopped_after(cmd + out, delay, signal.SIGINT, tmp_path / f"log{i}", env)
        assert rc == 130, (delay, rc, text[-2000:])
        _no_crash(text)
        assert "interrupted" in text.splitlines()[-1], text[-2000:]


@pytest.mark.slow  # (~50 s: four start-ups of an evaluation)
@pytest.mark.skipif(not hasattr(os, "killpg"), reason="POSIX process groups")
def test_evaluate_stopped_anywhere_is_one_line_and_exit_128_plus_signal(tmp_path):
    """`experiments.evaluate` stopped while it compiles and evaluates (cold compilation cache):
    Ctrl-C used to print a KeyboardInterrupt traceback and, landing inside XLA's compiler, crash
    the process at exit (SIGSEGV). Now: one line, exit 130 (SIGTERM: 143), nothing written."""
    run = ROOT / "results" / "restaurant" / "main-default"
    env = {**_env(), "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "cache")}
    cases = [(3.0, signal.SIGINT), (6.0, signal.SIGINT), (9.0, signal.SIGINT)]
    cases.append((5.0, signal.SIGTERM))
    for i, (delay, sig) in enumerate(cases):
        log, out = tmp_path / f"log{i}", tmp_path / f"eval{i}"
        cmd = [sys.executable, "-m", "experiments.evaluate", str(run), "--split", "val"]
        cmd += ["--task-seeds", "1", "--figures", "none", "--out", str(out)]
        rc, text = _stopped_after(cmd, delay, sig, log, env)
        assert rc == 128 + int(sig), (delay, rc, text[-2000:])
        _no_crash(text)
        assert text.splitlines()[-1].startswith("interrupted before the evaluation finished")
        assert not (out / "results.json").exists()


@pytest.mark.slow  # (~70 s: two start-ups and a resumed smoke run)
@pytest.mark.skipif(not hasattr(os, "killpg"), reason="POSIX process groups")
def test_grbal_ctrl_c_is_one_line_exit_130_and_resumes(tmp_path):
    """`experiments.grbal` stopped by Ctrl-C during its start-up (cold compilation cache): it
    used to print a KeyboardInterrupt traceback and could crash at exit (SIGSEGV). Now: one line,
    exit 130, the run folder released, and the command the line names finishes the run: the same
    command before the run's config is written, with --resume after. The delays count from the
    command's first line: a signal during its module imports, before `main` runs, is Python's own
    KeyboardInterrupt."""
    env = {**_env(), "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "cache")}
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "experiments.grbal", "--preset", "smoke", "--iterations", "2"]
    cmd += ["--no-progress", "--out", str(out)]
    for i, delay in enumerate((3.0, 6.0)):
        go_on = ["--resume"] if (out / "config.json").is_file() else []
        log = tmp_path / f"log{i}"
        rc, text = _stopped_after(cmd + go_on, delay, signal.SIGINT, log, env, after="GrBAL")
        assert rc == 130, (delay, rc, text[-2000:])
        _no_crash(text)
        last = text.splitlines()[-1]
        assert last.startswith("interrupted"), text[-2000:]
        resume = "--resume" in last
        assert resume == (out / "config.json").is_file(), last
    again = cmd + (["--resume"] if resume else [])
    done = subprocess.run(again, cwd=ROOT, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (out / "results.json").is_file()


@pytest.mark.slow  # (~60 s: a GrBAL smoke run stopped after its first iteration, then resumed)
@pytest.mark.skipif(not hasattr(os, "killpg"), reason="POSIX process groups")
def test_grbal_ctrl_c_during_training_saves_the_iteration_and_resumes(tmp_path):
    """Ctrl-C once GrBAL trains: the iteration under way is finished and saved (it used to be
    lost back to the last scheduled checkpoint), the line says where, and --resume finishes the
    run with one metrics row per iteration."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "experiments.grbal", "--preset", "smoke", "--iterations", "3"]
    cmd += ["--no-progress", "--out", str(out)]
    log = tmp_path / "log"
    with open(log, "w") as f:
        proc = subprocess.Popen(
            cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=_env(), start_new_session=True
        )
        cond, t_end = rows_at_least(out, 1), time.monotonic() + 240
        while not cond():
            assert proc.poll() is None and time.monotonic() < t_end, log.read_text()[-2000:]
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)
        rc = proc.wait(timeout=240)
    text = log.read_text()
    assert rc == 130, text[-2000:]
    assert "Traceback" not in text, text[-2000:]
    last = text.splitlines()[-1]
    assert last.startswith("interrupted at iteration "), last
    n = int(last.split("interrupted at iteration ")[1].split(";")[0])
    assert 1 <= n < 3, last
    assert len(read_log(out / LOG_FILE)) == n
    assert (out / "checkpoints" / str(n)).is_dir()
    done = subprocess.run(cmd + ["--resume"], cwd=ROOT, env=_env(), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert [r["iteration"] for r in read_log(out / LOG_FILE)] == [1, 2, 3]
    assert (out / "results.json").is_file()
