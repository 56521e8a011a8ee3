"""Helpers of the fault-injection tests (tests/test_faults_*.py): the smoke run shrunk to a few
seconds (8 training tasks, tiny networks, a checkpoint every iteration), subprocesses of the
command line killed or interrupted at a condition, and the comparison of a resumed run with one
never stopped."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from mpcpearl_jax.cli.args import build_config, parser
from mpcpearl_jax.cli.train import main
from mpcpearl_jax.runfolder import LOG_FILE, read_log

ROOT = Path(__file__).resolve().parents[1]


# the smoke preset shrunk: 8 training tasks (one behaviour per layout), tiny networks, a
# checkpoint every iteration; one collection program (no posterior phase, all tasks visited)
SMALL = [
    "--preset",
    "smoke",
    "--no-progress",
    *("--set", 'task_options={"train_behaviours":1}'),
    *("--set", "pearl.hidden=[16,16]"),
    *("--set", "pearl.encoder_hidden=[16]"),
    *("--set", "pearl.latent_dim=3"),
    *("--set", "pearl.meta_batch=3"),
    *("--set", "pearl.batch_size=16"),
    *("--set", "pearl.context_size=8"),
    *("--set", "train.updates_per_iteration=3"),
    *("--set", "train.rl_capacity=400"),
    *("--set", "train.tasks_per_iteration=8"),
    *("--set", "train.posterior_episodes=0"),
    *("--set", "train.eval_interval=0"),
    *("--set", "train.checkpoint_interval=1"),
    *("--set", "train.keep_checkpoints=3"),
]


ITERATIONS = 6


TIMING = {"collect_s", "update_s", "train_s", "wall_s", "eval_s", "mpc_solve_s", "mpc_host_s"}


def train_only(cfg, out, resume: bool = False, handle_sigint: bool = False):
    """Train `cfg` into `out` in the training command's iterations mode without its final
    evaluation (`open_session`, `train_iterations`): -> (trainer, state); a stop or a divergence
    raises as `mpcpearl_jax.train` does."""
    from mpcpearl_jax.training.run import open_session, train_iterations

    with open_session(cfg, out, resume) as sess:
        state, info = train_iterations(sess, handle_sigint=handle_sigint)
        if "error" in info:
            raise info["error"]
        return sess.trainer, state


# train only (the command line without its final evaluation), as the command line trains
DRIVER = (
    "import sys\n"
    f"sys.path.insert(0, {str(ROOT / 'tests')!r})\n"
    "from mpcpearl_jax.cli.args import build_config, parser\n"
    "from faults_helpers import train_only\n"
    "a = parser('restaurant').parse_args(sys.argv[1:])\n"
    "train_only(build_config(a, 'restaurant'), a.out, resume=a.resume, handle_sigint=True)\n"
)


def small_args(eps: float, out: Path, iterations: int = ITERATIONS, *extra: str) -> list[str]:
    return [*SMALL, "--eps", str(eps), "--iterations", str(iterations), "--out", str(out), *extra]


def small_cfg(eps: float, iterations: int = ITERATIONS):
    return build_config(
        parser("restaurant").parse_args(small_args(eps, Path("x"), iterations)), "restaurant"
    )


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    cache = jax.config.jax_compilation_cache_dir  # the test session's cache (conftest)
    if cache:
        env["JAX_COMPILATION_CACHE_DIR"] = cache
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.5"
        env["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    return env


def spawn(args: list[str], log: Path, cli: bool = False, **kw) -> subprocess.Popen:
    cmd = (
        [sys.executable, "-m", "experiments.restaurant"] if cli else [sys.executable, "-c", DRIVER]
    )
    out = open(log, "a")  # noqa: SIM115 (closed with the process)
    kw.setdefault("env", _env())
    return subprocess.Popen(cmd + args, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, **kw)


def kill_when(proc: subprocess.Popen, cond, timeout: float = 240.0) -> bool:
    """SIGKILL proc as soon as cond() holds (polled every ms); False if proc ended first."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if proc.poll() is not None:
            return False
        if cond():
            proc.kill()
            proc.wait()
            return True
        time.sleep(0.001)
    proc.kill()
    raise AssertionError("kill condition not reached in time")


def writing_checkpoint(run: Path, min_step: int = 0):
    """A checkpoint of step >= min_step is being written (orbax's temporary folder exists)."""

    def cond() -> bool:
        d = run / "checkpoints"
        try:
            names = [p.name for p in d.iterdir()]
        except OSError:
            return False
        return any("tmp" in n and int(n.split(".")[0]) >= min_step for n in names if n[0].isdigit())

    return cond


def rows_at_least(run: Path, n: int):
    def cond() -> bool:
        try:
            return (run / LOG_FILE).read_bytes().count(b"\n") >= n
        except OSError:
            return False

    return cond


def final_checkpoint(run: Path) -> tuple[int, dict]:
    import orbax.checkpoint as ocp

    steps = sorted(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit())
    with ocp.StandardCheckpointer() as c:
        tree = c.restore((run / "checkpoints" / str(steps[-1]) / "default").absolute())
    return steps[-1], tree


def metric_rows(run: Path) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING} for r in read_log(run / LOG_FILE)]


def assert_same_run(ref: Path, run: Path) -> None:
    """Same final checkpoint (every array bit for bit), policy file and metrics (timings aside)."""
    (s_ref, t_ref), (s_run, t_run) = final_checkpoint(ref), final_checkpoint(run)
    assert s_ref == s_run
    flat_ref = jax.tree_util.tree_leaves_with_path(t_ref)
    flat_run = jax.tree_util.tree_leaves_with_path(t_run)
    assert [p for p, _ in flat_ref] == [p for p, _ in flat_run]
    for (path, a), (_, b) in zip(flat_ref, flat_run, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=str(path))
    assert (ref / "policy.msgpack").read_bytes() == (run / "policy.msgpack").read_bytes()
    assert metric_rows(ref) == metric_rows(run)


def _interrupted_at(text: str) -> int:
    """The iteration of the one 'interrupted at iteration N; continue with --resume' line."""
    lines = [x for x in text.splitlines() if x.startswith("interrupted at iteration")]
    assert len(lines) == 1 and lines[0].endswith("; continue with --resume"), text
    return int(lines[0].split()[3].rstrip(";"))


def signal_group_when(
    proc: subprocess.Popen, cond, sig: int, log: Path, *, after_s: float = 0.0, timeout=240.0
) -> int:
    """Send `sig` to the whole process group of proc (started with start_new_session=True), as a
    terminal's Ctrl-C does, once cond() holds and `after_s` seconds more have passed; -> its
    exit code. The group is killed if it is still there afterwards (a failed test leaves no
    training behind)."""
    try:
        deadline = time.monotonic() + timeout
        while not cond():
            assert proc.poll() is None, log.read_text()[-3000:]
            assert time.monotonic() < deadline, "the condition was not reached in time"
            time.sleep(0.005)
        time.sleep(after_s)
        os.killpg(proc.pid, sig)
        return proc.wait(timeout=90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _sigint_when(proc: subprocess.Popen, cond, timeout: float = 240.0) -> float:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        assert proc.poll() is None, "the run ended before Ctrl-C"
        if cond():
            proc.send_signal(signal.SIGINT)
            return time.monotonic()
        time.sleep(0.001)
    proc.kill()
    raise AssertionError("condition not reached")


def _one_line_error(capsys, argv, env="restaurant", **extra) -> str:
    assert main(env, argv, **extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def _make_unwritable(folder: Path):
    """Make folder unwritable (chmod; for root, which writes anywhere, the immutable attribute);
    returns the undo function."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        return lambda: folder.chmod(0o755)
    chattr = shutil.which("chattr")
    if chattr and subprocess.run([chattr, "+i", str(folder)], capture_output=True).returncode == 0:
        return lambda: subprocess.run([chattr, "-i", str(folder)], capture_output=True)
    pytest.skip("cannot make a folder unwritable for root here")


LEARNING_SMALL = [a for a in SMALL if a != "--no-progress"]


def learning_args(out: Path, minutes: float, every: float, *extra: str) -> list[str]:
    return [*LEARNING_SMALL, "--eps", "0", "--minutes", str(minutes)] + [
        *("--eval-minutes", str(every), "--out", str(out), *extra)
    ]
