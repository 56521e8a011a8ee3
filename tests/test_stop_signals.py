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

import numpy as np
import pytest
from faults_helpers import (
    ROOT,
    _env,
    _interrupted_at,
    rows_at_least,
    signal_group_when,
    small_args,
    spawn,
)

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

    def ready() -> bool:  # two iterations logged and the two MPC workers up
        workers[:] = _mpc_workers(proc.pid) if rows_at_least(run, 2)() else []
        return len(workers) >= 2

    rc = signal_group_when(proc, ready, sig, log)  # what Ctrl-C in a terminal does
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
from mpcpearl_jax.mpc.pool import make_pool, stop_signals_blocked

if __name__ == "__main__":
    got = []
    signal.signal(signal.SIGINT, lambda s, f: got.append(s))
    signal.signal(signal.SIGHUP, lambda s, f: got.append(s))
    pool = make_pool(2)
    with stop_signals_blocked():
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
    cases = [(3.0, signal.SIGINT), (6.0, signal.SIGINT), (9.0, signal.SIGINT)]
    cases.append((5.0, signal.SIGTERM))
    for i, (delay, sig) in enumerate(cases):
        log, out = tmp_path / f"log{i}", tmp_path / f"eval{i}"
        # a cold cache for each case, and eight task seeds: the evaluation (about 13 s on a quiet
        # 2-core CPU) outlasts the last delay
        env = {**_env(), "JAX_COMPILATION_CACHE_DIR": str(tmp_path / f"cache{i}")}
        cmd = [sys.executable, "-m", "experiments.evaluate", str(run), "--split", "val"]
        cmd += ["--task-seeds", "1-8", "--figures", "none", "--out", str(out)]
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


_GUARDED = """
import os, signal, sys, time
sys.argv[0] = "-m"  # as `python -m PACKAGE.MODULE` runs its package's __init__
from mpcpearl_jax.cli.stopping import guard_program, stoppable
guard_program()
if sys.argv[1] == "after":
    stoppable(lambda: 0)()  # a command that returned: its output is complete
print("ready", flush=True)
os.kill(os.getpid(), int(sys.argv[2]))
time.sleep(30)
"""


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signals")
def test_a_stop_outside_a_commands_own_handling_is_one_line_and_exit_128_plus_signal(tmp_path):
    """`guard_program` (run by the experiments, lab and benchmarks packages for `python -m`):
    a stop signal during a command's imports, or in the interpreter's exit after the command
    returned (evaluate's SIGTERM just after "wrote results.json" exited 143 without a word),
    ends the process with one line and exit code 128 + the signal."""
    script = tmp_path / "guarded.py"
    script.write_text(_GUARDED)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    cases = [
        ("before", signal.SIGINT, "interrupted (Ctrl-C)"),
        (
            "after",
            signal.SIGTERM,
            "interrupted (SIGTERM) after the command finished (its output is complete)",
        ),
        (
            "after",
            signal.SIGHUP,
            "interrupted (SIGHUP) after the command finished (its output is complete)",
        ),
    ]
    for when, sig, line in cases:
        cmd = [sys.executable, str(script), when, str(int(sig))]
        done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)
        assert done.returncode == 128 + sig, (when, sig, done.stderr)
        assert done.stdout == "ready\n" and done.stderr == line + "\n", (when, done.stderr)


@pytest.mark.slow  # (~60 s: nine start-ups)
@pytest.mark.skipif(not hasattr(os, "killpg"), reason="POSIX process groups")
def test_export_gp_mpc_sidewalk_and_benchmarks_stopped_anywhere_are_one_line(tmp_path):
    """`experiments.export`, `experiments.gp_mpc`, `experiments.sidewalk` and a benchmark
    stopped during their imports, while they compile (cold compilation cache) and while they
    run: Ctrl-C used to print a KeyboardInterrupt traceback (export at 2.5 s) and crash the
    process at exit (gp_mpc at 10 s: SIGSEGV). Now: one line, exit 128 + the signal, nothing
    written."""
    env = {**_env(), "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "cache")}
    run = ROOT / "results" / "restaurant" / "main-default"
    m = [sys.executable, "-m"]
    export = [*m, "experiments.export", str(run), "--platforms", "cpu"]
    gp_mpc = [*m, "experiments.gp_mpc", "--split", "test", "--max-tasks", "4"]
    sidewalk = [*m, "experiments.sidewalk", "--preset", "smoke", "--no-progress"]
    bench = [*m, "benchmarks.env_throughput", "--out", str(tmp_path / "bench")]
    cases = [
        (export, 0.5, signal.SIGINT),
        (export, 2.5, signal.SIGINT),
        (export, 2.0, signal.SIGTERM),
        (gp_mpc, 0.5, signal.SIGINT),
        (gp_mpc, 6.0, signal.SIGINT),
        (gp_mpc, 10.0, signal.SIGTERM),
        (sidewalk, 0.5, signal.SIGINT),
        (bench, 0.5, signal.SIGINT),
        (bench, 6.0, signal.SIGINT),
    ]
    for i, (cmd, delay, sig) in enumerate(cases):
        out = tmp_path / f"out{i}"
        args = cmd + ["--out", str(out / "policy.export")] if cmd is export else cmd
        args = args + ["--out", str(out)] if cmd in (gp_mpc, sidewalk) else args
        rc, text = _stopped_after(args, delay, sig, tmp_path / f"log{i}", env)
        assert rc == 128 + int(sig), (cmd[2], delay, rc, text[-2000:])
        _no_crash(text)
        assert text.splitlines()[-1].startswith("interrupted"), (cmd[2], delay, text[-2000:])
        assert not list(out.glob("*.json")) and not (out / "policy.export").exists()


def test_the_sqp_passes_on_a_ctrl_c_that_osqp_took_and_solves_again(monkeypatch):
    """OSQP takes SIGINT with a handler of its own while it solves ("Solver interrupted",
    status OSQP_SIGINT): a Ctrl-C during training printed that line, the training never saw it
    and ran to its end. The SQP now raises the signal again for Python's handler (here one that
    records it, as the training's stop flag does) and solves the QP again: the same plan as
    without the signal."""
    import types

    import osqp

    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import MPCConfig, RowProblem, SQPSolver, solver_params
    from mpcpearl_jax.mpc.qp_osqp import OSQPSettings

    cfg = MPCConfig()
    p = solver_params(cfg, make_env("restaurant").config, 1)
    rng = np.random.default_rng(0)
    samples = 0.3 * rng.standard_normal((cfg.horizon, 2, cfg.num_samples, 2))
    box = np.array([[3.0, 3.5]])
    prob = RowProblem(
        np.array([-3.0, 0.0, 0.0]),
        np.array([4.0, 0.0]),
        samples,
        np.ones(2, bool),
        box,
        box,
        np.ones(1),
    )
    qp = OSQPSettings.from_config(cfg)
    clean = SQPSolver(p, qp).solve(prob)
    solve, taken = osqp.OSQP.solve, []

    def swallowing(self, *a, **kw):  # the first solve is cut short by a Ctrl-C OSQP took
        if not taken:
            taken.append(True)
            info = types.SimpleNamespace(status_val=osqp.SolverStatus.OSQP_SIGINT, iter=1)
            return types.SimpleNamespace(info=info, x=None)
        return solve(self, *a, **kw)

    monkeypatch.setattr(osqp.OSQP, "solve", swallowing)
    got: list[int] = []
    old = signal.signal(signal.SIGINT, lambda s, f: got.append(s))
    try:
        again = SQPSolver(p, qp).solve(prob)
    finally:
        signal.signal(signal.SIGINT, old)
    assert taken and got == [signal.SIGINT]
    np.testing.assert_array_equal(again.u, clean.u)
    assert (again.reason, again.qp_iters) == (clean.reason, clean.qp_iters)


_OSQP_STOP = """
import os, signal, subprocess, sys
import numpy as np, scipy.sparse as sp, osqp
from mpcpearl_jax.mpc.qp_osqp import solve_through_stops


def problem():  # a QP OSQP takes about a second or more for
    n = 3000
    m = sp.random(n, n, density=0.01, random_state=0)
    p = (m @ m.T + sp.eye(n)).tocsc()
    a = sp.vstack([sp.eye(n), sp.random(n, n, density=0.01, random_state=1)]).tocsc()
    q = np.random.default_rng(0).normal(size=n)
    s = osqp.OSQP()
    s.setup(p, q, a, -np.ones(2 * n), np.ones(2 * n), eps_abs=1e-9, eps_rel=1e-9, rho=0.1,
            adaptive_rho_interval=25, max_iter=100000, verbose=False)
    return s, np.zeros(n), np.zeros(2 * n)


def solve(interrupt):  # -> (status, x, Python's handler raised)
    s, x0, y0 = problem()
    if interrupt:  # SIGINT to this process 0.3 s into the solve
        subprocess.Popen(["sh", "-c", f"sleep 0.3; kill -INT {os.getpid()}"])
    try:
        res = solve_through_stops(s, x0, y0, 0.1)
    except KeyboardInterrupt:
        return None, None, True
    return int(res.info.status_val), res.x, False


def in_worker():  # as a pool worker (`pool_worker_init`: SIGINT ignored)
    status, x, raised = solve(True)
    return status, x.tolist(), raised


if __name__ == "__main__":
    status, clean, _ = solve(False)
    got = []
    signal.signal(signal.SIGINT, lambda s, f: got.append(s))  # a stop flag, as the training's
    st, x, _ = solve(True)
    print("flag", st == status and np.array_equal(x, clean), got == [signal.SIGINT], flush=True)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    print("raise", solve(True)[2], flush=True)
    from mpcpearl_jax.mpc.pool import make_pool

    pool = make_pool(1)
    st, x, raised = pool.submit(in_worker).result()
    print("worker", st == status and np.array_equal(x, clean) and not raised, flush=True)
    pool.shutdown()
"""


@pytest.mark.slow  # (~15 s: five solves of a large QP)
def test_a_ctrl_c_osqp_takes_during_a_solve_reaches_python_and_the_solve_is_redone(tmp_path):
    """A real SIGINT during a real OSQP solve (`mpc.qp_osqp.solve_through_stops`): in the
    training process it reaches Python's handler (a stop flag records it; the default handler
    raises KeyboardInterrupt) and the QP is solved again to the same solution; in an MPC pool
    worker, which ignores SIGINT, the solution is the same as without the signal."""
    script = tmp_path / "osqp_stop.py"
    script.write_text(_OSQP_STOP)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=240
    )
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.split("\n")
    rows = [x for x in lines if x.split(" ")[0] in ("flag", "raise", "worker")]
    assert rows == ["flag True True", "raise True", "worker True"], done.stdout
