"""Fault injection: kill -9 at any moment then --resume (ends identical to a run never stopped,
with and without the MPC), Ctrl-C, corrupt checkpoints, torn metrics lines, unwritable folders,
malformed data files, wrong options and wrong `load_policy` inputs; learning-curve runs stopped
and resumed, a second writer on a run folder, --resume with nothing to resume, non-finite
parameters and JSON values, an unreachable coordinator, a full disk, unwritable evaluation
folders, reversed ranges, oversized size fields and a GrBAL folder given to `load_policy`.

The runs are a smoke run shrunk to a few seconds (8 training tasks, tiny networks); the long
variants (the real command line, kill points at random moments, eps 0 and 0.2) are marked slow.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.common import build_config, main, parser
from mpcpearl_jax.deploy.policy import load_policy
from mpcpearl_jax.envs.sidewalk.loader import DataFormatError, load_eth_ucy
from mpcpearl_jax.envs.types import ConfigError
from mpcpearl_jax.training.checkpoint import CheckpointError
from mpcpearl_jax.training.run import (
    LOG_FILE,
    RunDirError,
    check_writable,
    prepare,
    read_log,
    train,
)
from mpcpearl_jax.training.trainer import IterationAbandoned, Trainer

ROOT = Path(__file__).resolve().parents[1]
ZARA = ROOT.parent / "shared" / "data" / "crowds_zara01.txt"

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
# train only (the command line without its final evaluation), as the command line trains
DRIVER = (
    "import sys\n"
    "from experiments.common import build_config, parser\n"
    "from mpcpearl_jax.training.run import train\n"
    "a = parser('restaurant').parse_args(sys.argv[1:])\n"
    "train(build_config(a, 'restaurant'), a.out, resume=a.resume, progress=False,"
    " handle_sigint=True)\n"
)


def small_args(eps: float, out: Path, iterations: int = ITERATIONS, *extra: str) -> list[str]:
    return [*SMALL, "--eps", str(eps), "--iterations", str(iterations), "--out", str(out), *extra]


def small_cfg(eps: float, iterations: int = ITERATIONS):
    return build_config(
        parser("restaurant").parse_args(small_args(eps, Path("x"), iterations)), "restaurant"
    )


# --------------------------------------------------------------------------- helpers
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


@pytest.fixture(scope="module")
def ref0(tmp_path_factory) -> Path:
    """The uninterrupted eps-0 run (trained in this process)."""
    out = tmp_path_factory.mktemp("ref") / "eps0"
    train(small_cfg(0.0), out, progress=False)
    return out


# ------------------------------------------------------------------ kill -9 and resume
def test_mpc_collection_does_not_depend_on_earlier_iterations():
    """eps 0.2: iterations 2-3 rerun from a copy of the state after iteration 1, by the same
    trainer (whose MPC bridge and OSQP solvers have meanwhile solved iterations 2-3), give the
    same state bit for bit: no host-side MPC state (warm-start plans, OSQP's rho) leaks into
    later iterations, which is what makes a resumed run exact."""
    tr = Trainer(small_cfg(0.2))
    state, log = tr.iteration(tr.init_state())
    assert log["mpc_rows"] > 0
    snapshot = jax.tree_util.tree_map(jnp.copy, state)
    runs = []
    for start in (state, snapshot):
        s, logs = start, []
        for _ in range(2):
            s, lg = tr.iteration(s)
            logs.append({k: v for k, v in lg.items() if k not in TIMING})
        runs.append((jax.device_get(s), logs))
    (a, logs_a), (b, logs_b) = runs
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    assert logs_a == logs_b and logs_a[0]["mpc_rows"] > 0
    assert tr.bridge._episode is not None  # the collector stamps its batches of episodes


def test_osqp_solver_state_does_not_carry_between_solves():
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import MPCConfig, RowProblem, SQPSolver, solver_params

    cfg = MPCConfig()
    p = solver_params(cfg, make_env("restaurant").config, 1)
    rng = np.random.default_rng(0)
    probs = []
    for _ in range(12):
        x0 = np.array([rng.uniform(-4, -1), rng.uniform(-1, 1), rng.uniform(-0.5, 0.5)])
        centre = np.array([rng.uniform(-2, 2), rng.uniform(-1, 1)])
        samples = centre + 0.3 * rng.standard_normal((cfg.horizon, 2, cfg.num_samples, 2))
        box = np.array([[3.0, 3.5]])
        probs.append(
            RowProblem(x0, np.array([4.0, 0.0]), samples, np.ones(2, bool), box, box, np.ones(1))
        )
    reused = SQPSolver(p)
    for prob in probs:
        np.testing.assert_array_equal(reused.solve(prob).u, SQPSolver(p).solve(prob).u)


def test_bridge_forgets_plans_of_an_earlier_episode_batch():
    from mpcpearl_jax.envs import make_env
    from mpcpearl_jax.mpc import MPCConfig, make_mpc_bridge

    env = make_env("restaurant")
    bridge = make_mpc_bridge(env, MPCConfig())
    b, k, s = 2, bridge.cfg.horizon, 1
    z = np.zeros

    def host(stamp):  # a call where no row fires: only the memory bookkeeping runs
        bridge._host(
            z(b, bool), z((b, 3)), np.full(b, 6), z((b, 2)), z((b, s, 2)), z((b, s, 2)),
            z((b, s)), z((b, k, 2, 4, 2)), z((b, 2), bool), np.asarray(stamp), np.asarray(0),
        )  # fmt: skip

    host([1, 10, 20])
    bridge._plan_t[:] = 5  # plans made at t = 5 in this batch of episodes
    host([1, 10, 20])
    assert bridge._warm_plan(0, 6) is not None  # same episodes: warm start
    host([1, 10, 21])
    assert bridge._warm_plan(0, 6) is None  # new episodes: the old plans are gone
    bridge._plan_t[:] = 5
    host([0, 0, 0])  # no stamp (callers that run one batch): memory kept
    assert bridge._warm_plan(0, 6) is not None


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


# ------------------------------------------------------------------------------ Ctrl-C
def _interrupted_at(text: str) -> int:
    """The iteration of the one 'interrupted at iteration N; continue with --resume' line."""
    lines = [x for x in text.splitlines() if x.startswith("interrupted at iteration")]
    assert len(lines) == 1 and lines[0].endswith("; continue with --resume"), text
    return int(lines[0].split()[3].rstrip(";"))


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


def test_update_chunks_give_one_scan_and_answer_stop():
    """The update phase in chunks of 2 + 1 steps equals one scan of its 3 steps (same keys, bit
    for bit), and a stop request is answered between chunks."""
    tr = Trainer(small_cfg(0.0))  # 3 gradient steps per iteration
    state, _ = tr.initial_collection(tr.init_state())
    copy = jax.tree_util.tree_map(jnp.copy, state)
    one = tr._chunked_update_phase(state, None)  # chunk 25: one scan
    tr.update_chunk = 2
    chunked = tr._chunked_update_phase(copy, None)
    leaves = jax.tree_util.tree_leaves
    for x, y in zip(leaves(one), leaves(chunked), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    calls = []

    def stop() -> bool:
        calls.append(1)
        return len(calls) > 1

    with pytest.raises(IterationAbandoned):
        tr._chunked_update_phase(chunked[0], stop)
    assert len(calls) == 2  # one chunk ran, the second was not started


# ------------------------------------------------------------------ corrupt, torn, cut
# orbax leaves an unraisable warning behind when it fails to read the garbled checkpoint
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
    train(small_cfg(0.0), run, resume=True, progress=False)
    err = capsys.readouterr().err
    assert f"checkpoints/{ITERATIONS}: cannot restore" in err
    assert f"falling back to iteration {ITERATIONS - 1}" in err
    assert f"{run / LOG_FILE}: dropped a torn last line" in err
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
        prepare(small_cfg(0.0, 3), ref0, resume=True)
    assert main("restaurant", small_args(0.0, ref0, 3, "--resume")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--iterations 3 is below" in err[0]
    assert (ref0 / "config.json").read_bytes() == before  # untouched by a refused command


# ----------------------------------------------------------------- unwritable folders
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


def test_unwritable_checkpoints_folder_is_reported_before_training(tmp_path):
    run, log = tmp_path / "run", tmp_path / "log.txt"
    (run / "checkpoints").mkdir(parents=True)
    undo = _make_unwritable(run / "checkpoints")
    try:
        t0 = time.monotonic()
        proc = spawn(small_args(0.0, run), log, cli=True)
        assert proc.wait(timeout=60) == 2
        assert time.monotonic() - t0 < 30
    finally:
        undo()
    text = log.read_text()
    errors = [line for line in text.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, text
    assert errors[0].startswith(f"error: {run / 'checkpoints'}: not writable (")
    assert errors[0].endswith("); fix its permissions or choose another --out")
    assert "Traceback" not in text and not (run / "config.json").exists()


def test_run_folder_that_cannot_be_created_is_named(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(RunDirError, match=r"file/run: not writable"):
        check_writable(tmp_path / "file" / "run")


# ------------------------------------------------------------------ command-line errors
def _one_line_error(capsys, argv, env="restaurant", **extra) -> str:
    assert main(env, argv, **extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


@pytest.mark.parametrize(
    "sets, needle",
    [
        (["mpc.nosuch=1"], "MPCConfig has no field(s) ['nosuch']"),
        (["mpc.alpha=5"], "MPCConfig.alpha: must lie in (0, 1)"),
        (["env.nosuch=1"], "NavConfig has no field(s) ['nosuch']"),
        (["env.dt=-1"], "NavConfig.dt"),
        (["train.eps=true"], "TrainConfig.eps must be a number, not a boolean"),
        (["train.eps=True"], "TrainConfig.eps must be a number, not a boolean"),
        (["pearl.use_context=maybe"], "PearlConfig.use_context must be true or false"),
        (["train.iterations=false"], "TrainConfig.iterations must be an int, not a boolean"),
    ],
)
def test_config_errors_are_one_line_and_write_nothing(tmp_path, capsys, sets, needle):
    argv = ["--preset", "smoke", "--eps", "0", "--out", str(tmp_path / "r")]
    line = _one_line_error(capsys, argv + [a for s in sets for a in ("--set", s)])
    assert needle in line
    assert not (tmp_path / "r" / "config.json").exists()


def test_boolean_options_are_read_by_field_type():
    def cfg(*sets):
        argv = ["--preset", "smoke"] + [a for s in sets for a in ("--set", s)]
        return build_config(parser("restaurant").parse_args(argv), "restaurant")

    for text, value in [("False", False), ("false", False), ("0", False), ("True", True),
                        ("true", True), ("1", True)]:  # fmt: skip
        assert cfg(f"pearl.use_context={text}").pearl.use_context is value
        assert cfg(f"train.redraw_behaviours={text}").train.redraw_behaviours is value
    assert cfg("mpc.unsafe_recovery=False").mpc.unsafe_recovery is False
    assert cfg("train.eps=1").train.eps == 1 and cfg("mpc.r_safe=None").mpc.r_safe is None
    with pytest.raises(ConfigError, match="TrainConfig.eps"):
        cfg("train.eps=false")


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(ConfigError):
        main("restaurant", ["--preset", "smoke", "--set", "mpc.alpha=5", "--debug"])


def test_checkpoint_errors_are_one_line(tmp_path, capsys, ref0):
    line = _one_line_error(capsys, small_args(0.0, tmp_path / "nothing", 6, "--resume"))
    assert "no config.json" in line
    line = _one_line_error(capsys, [*small_args(0.0, ref0, 6, "--resume"), "--seed", "3"])
    assert "differs from the requested one in ['seed']" in line
    line = _one_line_error(capsys, small_args(0.0, ref0))
    assert "already holds checkpoints" in line


def test_compare_on_a_folder_that_is_not_a_run(tmp_path, capsys):
    from experiments import compare

    (tmp_path / "empty").mkdir()
    assert compare.main([str(tmp_path / "empty"), "--out", str(tmp_path / "cmp")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {tmp_path / 'empty'}: not a run directory (no config.json)"]


# ---------------------------------------------------------------------------- data files
BAD_DATA = {
    "binary.bin": bytes(range(256)) * 8,
    "nul.txt": b"0 1 2.0 3.0\n\x00\x00\x00\n",
    "nan.txt": b"0 1 2.0 3.0\n10 1 nan 3.0\n",
    "inf.txt": b"0 1 2.0 inf\n",
    "columns.txt": b"0 1 2.0\n",
    "words.txt": b"frame ped x y\n",
    "empty.txt": b"\n# only a comment\n",
}


@pytest.mark.parametrize("name", sorted(BAD_DATA))
def test_malformed_data_files_are_named(tmp_path, capsys, name):
    path = tmp_path / name
    path.write_bytes(BAD_DATA[name])
    with pytest.raises(DataFormatError, match=str(path)):
        load_eth_ucy(path)
    argv = ["--preset", "smoke", "--data", str(path), "--out", str(tmp_path / "r")]
    line = _one_line_error(capsys, argv, env="sidewalk", online_eval=True, mpc={"v_max": None})
    assert str(path) in line and not (tmp_path / "r" / "config.json").exists()


@pytest.mark.skipif(not ZARA.is_file(), reason="UCY Zara 01 not in ../shared/data")
def test_real_data_file_still_loads():
    scene = load_eth_ucy(ZARA)
    assert scene.num_pedestrians > 100 and np.all(np.isfinite(scene.xy))


# ---------------------------------------------------------------------------- load_policy
def test_load_policy_checks_shapes_and_values(ref0):
    pol = load_policy(ref0)
    o, d = pol.obs_dim, pol.context_dim
    assert d == 2 * o + 3
    ctx = jnp.zeros((10, d))
    with pytest.raises(ValueError, match=rf"obs: expected shape \[\.\.\., {o}\], got \({o + 3},\)"):
        pol(jnp.zeros(o + 3), ctx)
    with pytest.raises(ValueError, match=rf"context: expected shape \[C, {d}\]"):
        pol(jnp.zeros(o), jnp.zeros((10, d + 1)))
    with pytest.raises(ValueError, match=rf"context: expected shape \[C, {d}\]"):
        pol.infer_z(jnp.zeros(d))
    with pytest.raises(ValueError, match="obs: contains NaN or inf"):
        pol(jnp.full(o, jnp.nan), ctx)
    with pytest.raises(ValueError, match="context: contains NaN or inf"):
        pol(jnp.zeros(o), ctx.at[0, 0].set(jnp.inf))
    with pytest.raises(ValueError, match=r"mask: expected shape \[10\]"):
        pol.infer_z(ctx, jnp.ones(3))
    with pytest.raises(ValueError, match=r"z: expected shape"):
        pol.act(jnp.zeros((4, o)), jnp.zeros((4, pol.latent_dim + 1)))
    a = pol(jnp.zeros((4, o)), ctx)
    assert a.shape == (4, 2) and bool(jnp.all(jnp.isfinite(a)))
    act, infer_z = pol.jit()  # the fast path: shapes checked when traced, values not
    with pytest.raises(ValueError, match="obs: expected shape"):
        act(jnp.zeros(o + 3), jnp.zeros(pol.latent_dim))
    assert bool(jnp.all(jnp.isnan(act(jnp.full(o, jnp.nan), infer_z(ctx)))))


def test_mpc_pool_workers_exit_when_the_training_process_is_killed(tmp_path):
    """A SIGKILLed parent leaves no MPC worker behind (watch_parent)."""
    script = tmp_path / "parent.py"
    script.write_text(
        "import os, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from multiprocessing import get_context\n"
        "from mpcpearl_jax.mpc.solver import watch_parent\n"
        "if __name__ == '__main__':\n"
        "    pool = ProcessPoolExecutor(2, mp_context=get_context('spawn'),\n"
        "                               initializer=watch_parent, initargs=(os.getpid(), 0.2))\n"
        "    pids = set(pool.submit(os.getpid).result() for _ in range(4))\n"
        "    print(' '.join(map(str, pids)), flush=True)\n"
        "    time.sleep(60)\n"
    )
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    pids = [int(p) for p in proc.stdout.readline().split()]
    assert pids
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 10
    alive = pids
    while alive and time.time() < deadline:
        time.sleep(0.2)
        alive = [p for p in pids if _alive(p)]
    assert not alive, f"orphaned MPC workers {alive}"


def _alive(pid: int) -> bool:
    import os

    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped) counts as gone
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except OSError:
        return False


# ------------------------------------------- learning runs, one writer, nothing lost or non-finite
LEARNING_SMALL = [a for a in SMALL if a != "--no-progress"]


def learning_args(out: Path, minutes: float, every: float, *extra: str) -> list[str]:
    return [*LEARNING_SMALL, "--eps", "0", "--minutes", str(minutes)] + [
        *("--eval-minutes", str(every), "--out", str(out), *extra)
    ]


class _Tick:
    """A fake clock for `experiments.learning.main`: every call is one second later, so that each
    iteration takes one training second; once metrics.jsonl in `sigint_log` holds `sigint_rows`
    rows, the next call sends this process a SIGINT (a real Ctrl-C, handled by the harness)."""

    def __init__(self, sigint_log: Path | None = None, sigint_rows: int = 0):
        self.t, self.log, self.rows, self.sent = 0.0, sigint_log, sigint_rows, False

    def __call__(self) -> float:
        if self.log is not None and not self.sent and rows_at_least(self.log, self.rows)():
            self.sent = True
            os.kill(os.getpid(), signal.SIGINT)
        self.t += 1.0
        return self.t


def _points(run: Path) -> list[dict]:
    skip = {"wall_minutes", "eval_s"}
    rec = json.loads((run / "curve.json").read_text())
    return [{k: v for k, v in p.items() if k not in skip} for p in rec["points"]]


def test_learning_run_stops_on_ctrl_c_and_resumes_exactly(tmp_path, monkeypatch, capsys):
    """experiments.learning stopped by Ctrl-C in its fifth iteration (a fake clock: one second per
    iteration, 6 s of budget, an evaluation every 3 s) saves iteration 4 and exits 130 with one
    line; --resume ends identical to a run never stopped: checkpoint, policy, metrics and the
    curve points (the budget counts the 4 s already trained)."""
    from experiments import learning

    monkeypatch.setattr(
        "mpcpearl_jax.training.run.final_evaluation", lambda *a, **k: {}
    )  # not needed
    ref, run = tmp_path / "ref", tmp_path / "run"
    assert learning.main(learning_args(ref, 0.1, 0.05), clock=_Tick()) == 0
    capsys.readouterr()
    assert learning.main(learning_args(run, 0.1, 0.05), clock=_Tick(run, 4)) == 130
    err = [x for x in capsys.readouterr().err.splitlines() if not x.startswith("warning: 1-min")]
    assert [x for x in err if x.strip()][-1] == "interrupted at iteration 4; continue with --resume"
    assert "Traceback" not in "\n".join(err)
    assert (run / "checkpoints" / "4").is_dir() and len(read_log(run / LOG_FILE)) == 4
    rec = json.loads((run / "curve.json").read_text())
    assert rec["stopped"] == "interrupted" and [p["iteration"] for p in rec["points"]] == [0, 3]
    assert json.loads((run / "config.json").read_text())["train"]["iterations"] == 4
    assert learning.main(learning_args(run, 0.1, 0.05, "--resume"), clock=_Tick()) == 0
    assert_same_run(ref, run)
    assert _points(ref) == _points(run) and [p["iteration"] for p in _points(run)] == [0, 3, 6]
    assert json.loads((run / "curve.json").read_text())["resumed_at_iteration"] == 4


@pytest.mark.slow  # the Ctrl-C resume of the same harness is tested exactly above (~35 s)
def test_learning_run_ctrl_c_then_kill9_then_resume(tmp_path, monkeypatch):
    """The command line: Ctrl-C gives exit 130 and one line within seconds, with the checkpoint,
    config.json and curve saved; a --resume killed with SIGKILL loses at most the iteration under
    way (a checkpoint every iteration here); the next --resume continues the curve and the log
    where the last checkpoint left them."""
    from experiments import learning

    run, log = tmp_path / "run", tmp_path / "log.txt"
    cmd = [sys.executable, "-m", "experiments.learning", *learning_args(run, 10, 5)]
    with open(log, "a") as f:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=_env())
    t_sig = _sigint_when(proc, rows_at_least(run, 2))
    assert proc.wait(timeout=60) == 130
    assert time.monotonic() - t_sig < 15
    text = log.read_text()
    n = _interrupted_at(text)
    assert "Traceback" not in text
    assert n >= 2 and (run / "checkpoints" / str(n)).is_dir()
    assert json.loads((run / "curve.json").read_text())["stopped"] == "interrupted"
    assert json.loads((run / "config.json").read_text())["train"]["iterations"] == n
    with open(log, "a") as f:
        proc = subprocess.Popen(
            [*cmd, "--resume"], cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=_env()
        )
    assert kill_when(proc, rows_at_least(run, n + 2))
    before = read_log(run / "curve-points.jsonl")
    monkeypatch.setattr("mpcpearl_jax.training.run.final_evaluation", lambda *a, **k: {})
    # a budget already spent: no further iteration, the last point evaluated, the curve written
    assert learning.main(learning_args(run, 0.01, 0.005, "--resume")) == 0
    rows = read_log(run / LOG_FILE)
    done = rows[-1]["iteration"]
    assert [r["iteration"] for r in rows] == list(range(1, done + 1)) and done >= n + 1
    points = read_log(run / "curve-points.jsonl")
    kept = [p for p in before if p["iteration"] <= done]
    assert points[: len(kept)] == kept and points[-1]["iteration"] == done
    assert json.loads((run / "curve.json").read_text())["iterations"] == done


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
    sess = prepare(small_cfg(0.0), run, resume=True)
    sess.ckpt.close()
    sess.lock.release()
    assert sess.done == 0 and "starting at iteration 0" in capsys.readouterr().err


def _hold_lock(folder: Path) -> subprocess.Popen:
    code = (
        "import sys, time\nfrom mpcpearl_jax.training.runlock import RunLock\n"
        "RunLock(sys.argv[1])\nprint('locked', flush=True)\ntime.sleep(600)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True, env=_env()
    )
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_one_writer_per_run_folder(tmp_path, ref0, capsys):
    """While another process holds a run folder, a new run, a --resume, the learning harness and
    GrBAL each stop with one line naming the holder's PID and write nothing; once the holder is
    killed (SIGKILL), its lock file no longer blocks anyone."""
    from experiments import grbal, learning
    from mpcpearl_jax.training.runlock import LOCK_FILE, RunLock

    new, old = tmp_path / "new", tmp_path / "old"
    shutil.copytree(ref0, old)
    before = (old / LOG_FILE).read_bytes()
    holders = [_hold_lock(new), _hold_lock(old)]
    try:
        busy = (
            "is writing this run folder; wait for it to end (or stop it), or choose another --out"
        )
        pid_new, pid_old = (f"PID {p.pid} {busy}" for p in holders)
        line = _one_line_error(capsys, small_args(0.0, new))
        assert line == f"error: {new}: {pid_new}"
        line = _one_line_error(capsys, small_args(0.0, old, 8, "--resume"))
        assert line == f"error: {old}: {pid_old}"
        assert learning.main(learning_args(new, 1, 0.5)) == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"error: {new}: {pid_new}"
        assert grbal.main(["--preset", "smoke", "--out", str(new)]) == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"error: {new}: {pid_new}"
        assert sorted(p.name for p in new.iterdir()) == [LOCK_FILE]
        assert (old / LOG_FILE).read_bytes() == before
    finally:
        for p in holders:
            p.kill()
            p.wait()
    with RunLock(new), RunLock(old):  # the stale lock files of killed holders
        assert (new / LOCK_FILE).read_text().split()[0] == str(os.getpid())


def _nan_policy(run: Path) -> Path:
    from flax import serialization

    pfile = run / "policy.msgpack"
    raw = serialization.msgpack_restore(pfile.read_bytes())
    nan = jax.tree_util.tree_map(lambda x: np.full_like(x, np.nan), raw)
    pfile.write_bytes(serialization.msgpack_serialize(nan))
    return pfile


def test_non_finite_parameters_are_refused_on_save_and_load(tmp_path, ref0, capsys):
    from experiments import evaluate
    from mpcpearl_jax.training.checkpoint import Checkpointer, save_params

    run = tmp_path / "run"
    shutil.copytree(ref0, run)
    pfile = _nan_policy(run)
    with pytest.raises(CheckpointError, match=rf"{pfile}: non-finite network parameters"):
        load_policy(run)
    assert evaluate.main([str(run), "--tasks", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {pfile}: non-finite network parameters")
    assert not (run / "eval").exists()
    params = {"policy": {"w": np.array([1.0, np.nan])}}
    with pytest.raises(CheckpointError, match="not saved: non-finite network parameters"):
        save_params(tmp_path / "p.msgpack", params)
    assert not (tmp_path / "p.msgpack").exists()
    ckpt = Checkpointer(tmp_path / "c")
    try:
        with pytest.raises(CheckpointError, match="policy.msgpack: not saved: non-finite"):
            ckpt.save(1, {"x": jnp.zeros(2)}, params)
    finally:
        ckpt.close()
    assert ckpt.steps() == [] and not (tmp_path / "c" / "policy.msgpack").exists()


def _strict(text: str):
    def refuse(token):
        raise AssertionError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def test_results_json_never_holds_nan_or_infinity(tmp_path, ref0, capsys):
    """One task: the standard error over tasks is undefined (NaN); results.json says null and
    why, in strict JSON."""
    from experiments import evaluate
    from mpcpearl_jax.training.checkpoint import strict_json

    doc = _strict(strict_json({"a": float("nan"), "b": [1.0, float("-inf")], "c": 2}))
    assert doc["a"] is None and doc["b"] == [1.0, None] and doc["c"] == 2
    assert set(doc["null_values"]) == {"a", "b[1]"} and "NaN" in doc["null_values"]["a"]
    out = tmp_path / "seeds"
    argv = [str(ref0), "--task-seeds", "0-0", "--tasks", "0", "--out", str(out)]
    assert evaluate.main(argv) == 0
    rec = _strict((out / "results.json").read_text())
    assert rec["pooled"]["SR"]["se"] is None and "pooled.SR.se" in rec["null_values"]


def test_unreachable_coordinator_is_a_one_line_error_in_bounded_time(tmp_path):
    """No coordinator at the address (process 1), or process 0 left alone: exit 2 and one line
    after --coordinator-timeout, not a C++ abort minutes later."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    cases = [("127.0.0.1:1", 1, "no answer within 3 s"), (f"127.0.0.1:{free}", 0, "not every")]
    for address, pid, needle in cases:
        t0 = time.monotonic()
        proc = subprocess.run(
            [sys.executable, "-m", "experiments.restaurant", "--preset", "smoke"]
            + ["--out", str(tmp_path / "r"), "--coordinator", address, "--num-processes", "2"]
            + ["--process-id", str(pid), "--coordinator-timeout", "3"],
            cwd=ROOT,
            env=_env(),
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 2, proc.stderr[-3000:]
        assert time.monotonic() - t0 < 60
        errors = [x for x in proc.stderr.splitlines() if x.startswith("error:")]
        assert len(errors) == 1 and errors[0].startswith(f"error: --coordinator {address}: ")
        assert needle in errors[0] and "Check failure" not in proc.stderr, proc.stderr
        assert not (tmp_path / "r").exists()


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
    train(small_cfg(0.0), run, resume=True, progress=False)
    assert_same_run(ref0, run)


def test_evaluate_checks_its_output_folder_and_ranges_first(tmp_path, ref0, capsys):
    """An unwritable --out stops before the evaluation; reversed ranges are one-line errors."""
    from experiments import evaluate

    locked = tmp_path / "locked"
    locked.mkdir()
    undo = _make_unwritable(locked)
    try:
        assert evaluate.main([str(ref0), "--animate", "--out", str(locked / "eval")]) == 2
    finally:
        undo()
    cap = capsys.readouterr()
    assert cap.err.strip().splitlines() == [
        f"error: --out {locked / 'eval'}: not writable ("
        + cap.err.split("not writable (", 1)[1].strip()
    ]
    assert "[evaluate]" not in cap.out and not (locked / "eval").exists()
    for argv, needle in (
        (["--task-seeds", "5-1"], "--task-seeds '5-1': the range 5-1 is reversed"),
        (["--tasks", "3-1"], "--tasks '3-1': the range 3-1 is reversed"),
        (["--tasks", "0,4-2"], "the range 4-2 is reversed"),
    ):
        assert evaluate.main([str(ref0), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err


def test_size_fields_are_bounded_before_anything_is_written(tmp_path, capsys):
    from experiments import grbal
    from mpcpearl_jax.training.resources import check_fits

    out = tmp_path / "g"

    def grbal_error(horizon: int) -> list[str]:
        argv = ["--preset", "smoke", "--set", f"grbal.plan_horizon={horizon}", "--out", str(out)]
        assert grbal.main(argv) == 2
        return capsys.readouterr().err.strip().splitlines()

    assert grbal_error(100000000) == [
        "error: GrbalConfig.plan_horizon: must be at most 1000, got 100000000"
    ]
    assert not out.exists()
    err = grbal_error(500)  # within the bound, beyond the episode
    assert len(err) == 1 and "plan_horizon: must not exceed the episode length 80" in err[0]
    assert not (out / "config.json").exists() and not (out / LOG_FILE).exists()
    run = tmp_path / "r"
    line = _one_line_error(capsys, small_args(0.0, run, 2, "--set", "train.rl_capacity=1000000000"))
    assert line.startswith("error: train.rl_capacity") and "would need" in line
    assert not (run / "config.json").exists() and not (run / LOG_FILE).exists()
    assert not (run / "checkpoints").exists()
    with pytest.raises(ConfigError, match=r"f: x would need 1.0 GiB of memory, 512 MiB are free"):
        check_fits(2**30, "x", "f", free=2**29)


def test_load_policy_on_a_grbal_run_says_what_it_is(tmp_path, capsys):
    from experiments import evaluate
    from mpcpearl_jax.grbal.config import GrbalExperimentConfig, preset

    run = tmp_path / "grbal"
    run.mkdir()
    (run / "config.json").write_text(GrbalExperimentConfig(grbal=preset("smoke")).to_json())
    with pytest.raises(
        CheckpointError, match=rf"{run}: a GrBAL run .* python -m experiments.evaluate scores it"
    ):
        load_policy(run)
    # experiments.evaluate scores GrBAL runs (tests/test_grbal.py); one without a saved model
    # gets one line naming the file
    assert evaluate.main([str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "policy.msgpack: no saved model" in err[0]
