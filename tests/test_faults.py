"""Fault injection: kill -9 at any moment then --resume (ends identical to a run never stopped,
with and without the MPC), Ctrl-C, corrupt checkpoints, torn metrics lines, unwritable folders,
malformed data files, wrong options and wrong `load_policy` inputs.

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
from mpcpearl_jax.checkpoint import CheckpointError, load_policy
from mpcpearl_jax.envs.sidewalk.loader import DataFormatError, load_eth_ucy
from mpcpearl_jax.envs.types import ConfigError
from mpcpearl_jax.run import LOG_FILE, RunDirError, check_writable, prepare, read_log, train
from mpcpearl_jax.trainer import IterationAbandoned, Trainer

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
TIMING = {"collect_s", "update_s", "wall_s", "eval_s", "mpc_solve_s", "mpc_host_s"}
# train only (the command line without its final evaluation), as the command line trains
DRIVER = (
    "import sys\n"
    "from experiments.common import build_config, parser\n"
    "from mpcpearl_jax.run import train\n"
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
    assert res[0] == res[1]
    assert (run / "learning_curves.png").is_file()


# ------------------------------------------------------------------------------ Ctrl-C
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
    lines = [x for x in text.splitlines() if x.startswith("interrupted at iteration")]
    assert len(lines) == 1 and lines[0].endswith("; continue with --resume"), text
    n = int(lines[0].split()[3].rstrip(";"))
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
