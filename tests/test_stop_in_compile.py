"""A stop signal that arrives while JAX compiles: JAX's compiler call returns at once with the
KeyboardInterrupt and XLA goes on compiling in a thread of its own. The command then ends with
its line and exit code without the interpreter's teardown, which, run under the live compilation,
crashed the process after its last line (a segmentation fault, exit 139); and a first stop during
the first iteration's compilation, where nothing is unsaved, takes effect at once instead of after
the compilation."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from faults_helpers import ROOT

# a command that compiles a program of many unrolled operations (tens of seconds to compile on a
# 2-core CPU): "command": under the command's own handling (every stop signal raises), "first":
# the first stop of a training where nothing is unsaved, "early": the same, the signal 1 s before
# the compilation starts, "unsaved": a finished iteration not yet saved (the stop only sets the
# flag); an exit hook shows the teardown ran
SCRIPT = """
import atexit, sys, time
import jax, jax.numpy as jnp
from mpcpearl_jax.cli.stopping import stoppable, stop_exit_code
from mpcpearl_jax.training import stopping
from mpcpearl_jax.training.loop import Progress

def program(x):
    for i in range(300):
        x = jnp.sin(x @ x.T + i) * 0.5 + jnp.cos(x)
    return x

@stoppable
def main(mode):
    lowered = jax.jit(program).lower(jnp.ones((64, 64)))
    where = Progress(iterations=int(mode == "unsaved"), saved=-1)
    t = time.monotonic()
    try:
        with stopping.stop_flag(mode != "command", where) as flag:
            print("compiling", flush=True)
            if mode == "early":
                time.sleep(1.5)  # the signal comes before the compilation starts
            lowered.compile()
            print("compiled", flush=True)
    except KeyboardInterrupt as e:
        print(type(e).__name__, "abandoned" if stopping.compile_abandoned else "", flush=True)
    return stop_exit_code()

atexit.register(lambda: print("teardown", flush=True))
sys.exit(main(sys.argv[1]))
"""


def _stop_during_compile(mode: str, timeout: float) -> tuple[int | None, str, float]:
    """Run SCRIPT in `mode` in a process group of its own, Ctrl-C to the group 0.5 s after it
    starts compiling: -> (exit code, or None if it ran past `timeout` after the signal, output,
    seconds from the signal to the exit)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT, mode],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert first.strip() == "compiling", first + proc.stdout.read()
        time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGINT)
        t = time.monotonic()
        try:
            out, _ = proc.communicate(timeout=timeout)
            return proc.returncode, out, time.monotonic() - t
        except subprocess.TimeoutExpired:
            return None, "", time.monotonic() - t
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="process groups (POSIX)")
def test_a_stop_inside_a_compilation_ends_the_command_without_the_teardown():
    """Ctrl-C during a compilation in a command: KeyboardInterrupt at once, the command's exit
    code 130, and no interpreter teardown under the compilation still running (the exit hook
    does not run; the process does not wait for the compilation)."""
    code, out, took = _stop_during_compile("command", timeout=20)
    assert code == 130, (code, out)
    assert out.splitlines()[-1:] == ["KeyboardInterrupt abandoned"], out
    assert took < 10


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="process groups (POSIX)")
def test_a_first_stop_during_a_compilation_with_nothing_unsaved_stops_at_once():
    """The first Ctrl-C of a training with no finished iteration unsaved, during a
    compilation: StopNow at once (before, the flag waited for the compilation and the phase
    after it). With an unsaved iteration the first Ctrl-C only sets the flag: the compilation
    finishes."""
    code, out, took = _stop_during_compile("first", timeout=20)
    assert code == 130, (code, out)
    lines = out.splitlines()
    assert lines[-1:] == ["StopNow abandoned"] and "compiled" not in lines, out
    assert took < 10


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="process groups (POSIX)")
def test_a_first_stop_just_before_a_compilation_stops_it_once_it_starts():
    """The first Ctrl-C with nothing unsaved, 1 s before a compilation starts (the flag is set
    outside it): the compilation that then starts is stopped too (StopNow), not waited for."""
    code, out, took = _stop_during_compile("early", timeout=20)
    assert code == 130, (code, out)
    lines = out.splitlines()
    assert lines[-1:] == ["StopNow abandoned"] and "compiled" not in lines, out
    assert took < 10


@pytest.mark.slow  # (the whole compilation: ~60 s on a loaded 2-core CPU)
@pytest.mark.skipif(not hasattr(os, "killpg"), reason="process groups (POSIX)")
def test_a_first_stop_with_an_unsaved_iteration_lets_the_compilation_finish():
    code, out, _ = _stop_during_compile("unsaved", timeout=400)
    assert code == 130, (code, out)
    assert out.splitlines()[-2:] == ["compiled", "teardown"], out


def _pool_workers(pid: int) -> int:
    """How many of pid's children are spawned processes (the MPC pool's workers)."""
    from pathlib import Path

    n = 0
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmd = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if int(stat[stat.rindex(")") + 2 :].split()[1]) == pid and b"spawn_main" in cmd:
            n += 1
    return n


@pytest.mark.slow  # (a training's start-up and the first seconds of its first iteration: ~40 s)
@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="needs /proc (Linux)")
def test_a_first_ctrl_c_in_the_first_iteration_takes_effect_within_seconds(tmp_path):
    """The command line with MPC infusion (eps 0.5, a pool of two workers): Ctrl-C to the whole
    group 3 s after the pool's workers start (the first rollout is traced, its programs are
    compiling and running): exit 130 within 30 s with the one line `interrupted at iteration 0;
    continue with --resume`, no traceback, no checkpoint (nothing was finished). Polled only
    before the updates, the stop waited for the whole collection of the first iteration (more
    than 90 s here on a loaded 2-core CPU, against 16 s)."""
    from faults_helpers import signal_group_when, small_args, spawn

    run, log = tmp_path / "run", tmp_path / "log.txt"
    proc = spawn(
        small_args(0.5, run, 3, "--set", "mpc.n_workers=2"), log, cli=True, start_new_session=True
    )
    t = {}

    def workers_up() -> bool:
        if _pool_workers(proc.pid) and "up" not in t:
            t["up"] = time.monotonic()
        return "up" in t

    code = signal_group_when(proc, workers_up, signal.SIGINT, log, after_s=3.0)
    took = time.monotonic() - t["up"] - 3.0
    text = log.read_text()
    assert code == 130, text[-3000:]
    assert took < 30, (took, text[-3000:])
    lines = [x for x in text.splitlines() if x.startswith("interrupted")]
    assert lines == ["interrupted at iteration 0; continue with --resume"], text[-3000:]
    assert "Traceback" not in text and "Segmentation" not in text
    assert not [p for p in (run / "checkpoints").iterdir() if p.name.isdigit()]
