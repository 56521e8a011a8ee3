"""Seeds sharded over devices and processes (`mpcpearl_jax.distributed`): the same per-seed
results as on one device.

Each run is a subprocess (`tests/sharding_worker.py`): the number of CPU devices is fixed when JAX
starts (XLA_FLAGS=--xla_force_host_platform_device_count=N). 4 seeds, smoke sizes, eps = 0 (pure
JAX: results agree to float rounding); the MPC bridge under sharding has its own (slow) test.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mpcpearl_jax.config import ExperimentConfig, validate
from mpcpearl_jax.distributed import initialize, make_mesh, select_devices
from mpcpearl_jax.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
WORKER = ROOT / "tests" / "sharding_worker.py"

# the smoke preset shrunk (as tests/faults_helpers.py): 8 training tasks, tiny networks, one
# collection program per iteration, a checkpoint every iteration
SMALL = [
    "--preset",
    "smoke",
    "--no-progress",
    "--seeds",
    "4",
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
]


def _env(devices: int) -> dict:
    env = dict(os.environ)
    flags = f"--xla_force_host_platform_device_count={devices}"  # beside the suite's own
    env["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {flags}".strip()
    return env


def _cmd(result: Path, out: Path, iterations: int, eps: float, *extra: str) -> list[str]:
    return [
        sys.executable,
        str(WORKER),
        str(result),
        *SMALL,
        *("--eps", str(eps), "--iterations", str(iterations), "--out", str(out)),
        *extra,
    ]


def _train(tmp: Path, name: str, devices: int = 1, iterations: int = 2, eps: float = 0.0, *extra):
    result = tmp / f"{name}.npz"
    cmd = _cmd(result, tmp / name, iterations, eps, *extra)
    r = subprocess.run(
        cmd, env=_env(devices), cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert r.returncode == 0, r.stderr[-4000:]
    return _load(result)


def _load(result: Path) -> tuple[dict, dict]:
    z = np.load(result)
    return {k: z[k] for k in z.files if k != "meta"}, json.loads(str(z["meta"]))


def _assert_same_per_seed(a, b, atol: float = 1e-6) -> None:
    (pa, ma), (pb, mb) = a, b
    assert sorted(pa) == sorted(pb)
    for k in pa:
        assert pa[k].shape[0] == 4  # every leaf holds the 4 seeds
        np.testing.assert_allclose(pa[k], pb[k], rtol=1e-5, atol=atol, err_msg=k)
    for k in ("return_per_seed", "SR_per_seed", "CFR_per_seed", "TT_per_seed"):
        np.testing.assert_allclose(ma["eval"][k], mb["eval"][k], rtol=1e-5, atol=1e-3, err_msg=k)


@pytest.fixture(scope="module")
def one_device(tmp_path_factory):
    run = _train(tmp_path_factory.mktemp("one"), "one", devices=1)
    assert run[1]["devices"] == 1 and run[1]["iteration"] == 2
    return run


@pytest.mark.slow  # 4 forced host devices against 1 (~90 s)
def test_four_devices_of_one_process_match_one_device(one_device, tmp_path):
    run = _train(tmp_path, "four", devices=4)
    assert run[1]["devices"] == 4
    _assert_same_per_seed(one_device, run)


@pytest.mark.slow  # sharded resume (~40 s)
def test_sharded_resume_matches_an_uninterrupted_run(one_device, tmp_path):
    """Stopped after iteration 1 on 4 devices (orbax checkpoint of the sharded state), resumed
    on 4 devices to iteration 2: the same as 2 iterations on one device."""
    _train(tmp_path, "part", devices=4, iterations=1)
    (tmp_path / "part.npz").rename(tmp_path / "first.npz")
    result = tmp_path / "resumed.npz"
    cmd = _cmd(result, tmp_path / "part", 2, 0.0, "--resume")
    r = subprocess.run(cmd, env=_env(4), cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-4000:]
    run = _load(result)
    assert run[1]["devices"] == 4 and run[1]["iteration"] == 2
    _assert_same_per_seed(one_device, run)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _two_processes(
    tmp: Path, name: str, iterations: int, *extra: str, eps: float = 0.0, timeout: int = 600
) -> tuple[dict, dict]:
    """2 processes x 2 devices on 127.0.0.1 (gloo collectives); process 0's result."""
    result = tmp / f"{name}.npz"
    port = _free_port()
    procs = []
    for pid in (1, 0):
        dist = ("--coordinator", f"127.0.0.1:{port}", "--num-processes", "2")
        cmd = _cmd(result, tmp / name, iterations, eps, *dist, "--process-id", str(pid), *extra)
        procs.append(
            subprocess.Popen(
                cmd, env=_env(2), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE
            )
        )
    errors = []
    for p in procs:
        try:
            _, err = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            _, err = p.communicate()
        if p.returncode != 0:
            errors.append(err.decode(errors="replace")[-3000:])
    assert not errors, errors
    return _load(result)


@pytest.mark.slow
def test_two_processes_of_two_devices_match_one_device(one_device, tmp_path):
    """Also: orbax saves the sharded state from both processes, and --resume with the same
    process count continues it."""
    run = _two_processes(tmp_path, "multi", 1)
    assert run[1]["devices"] == 4 and run[1]["processes"] == 2
    run = _two_processes(tmp_path, "multi", 2, "--resume")
    assert run[1]["iteration"] == 2
    _assert_same_per_seed(one_device, run)


@pytest.mark.slow
def test_sharded_mpc_collection_solves_on_every_shard(tmp_path):
    """eps = 0.2: the MPC bridge runs per shard (each device's host call solves its own fired
    rows). Each shard batches its GP predictions differently from the whole batch, so rows
    agree to float rounding only; episodes amplify that, hence loose bounds here (the pure-JAX
    tests above are tight)."""
    one = _train(tmp_path, "mpc1", devices=1, eps=0.2)
    four = _train(tmp_path, "mpc4", devices=4, eps=0.2)
    assert four[1]["devices"] == 4
    rows1, rows4 = one[1]["mpc_rows"], four[1]["mpc_rows"]
    assert min(rows4) > 0
    np.testing.assert_allclose(rows4, rows1, rtol=0.2)
    np.testing.assert_allclose(
        four[1]["eval"]["return_per_seed"], one[1]["eval"]["return_per_seed"], rtol=0.05
    )


@pytest.mark.slow
def test_two_processes_with_the_mpc_on_finish_and_log(tmp_path):
    """eps = 0.2 over 2 processes x 2 devices: each process solves its own shards' rows, the
    MPC counters are summed over the processes and the log is written (a float32 from the
    cross-process sum once broke the JSON log of process 0, and process 1 then waited forever)."""
    run = _two_processes(tmp_path, "multi_mpc", 1, eps=0.2, timeout=300)
    assert run[1]["processes"] == 2 and run[1]["iteration"] == 1
    assert min(run[1]["mpc_rows"]) > 0
    log = (tmp_path / "multi_mpc" / "metrics.jsonl").read_text().splitlines()
    rows = [json.loads(x) for x in log]
    assert rows and rows[-1]["mpc_rows"] > 0 and isinstance(rows[-1]["mpc_fallback_rate"], float)


# ----------------------------------------------------------- options (in process, 1 device)
def test_seed_count_must_split_evenly_over_the_devices():
    with pytest.raises(ConfigError, match=r"ExperimentConfig.devices: 4 seed\(s\) do not split"):
        validate(ExperimentConfig(seeds=4, devices=3))
    for bad in (-1, True, 1.5):
        with pytest.raises(ConfigError, match="ExperimentConfig.devices"):
            ExperimentConfig(seeds=4, devices=bad)
    assert ExperimentConfig(seeds=4, devices=2).devices == 2


def test_device_selection_in_one_process():
    import jax

    n = len(jax.devices())
    with pytest.raises(ConfigError, match=rf"{n + 1} asked, {n} available"):
        select_devices(n + 1, n + 1)
    assert len(select_devices(3, 0)) in (1, 3)  # as many as divide the seeds evenly
    if n == 1:
        assert make_mesh(4, 0) is None  # one device: no mesh, the unchanged program


def test_distributed_options_are_checked():
    assert initialize() is False
    with pytest.raises(ConfigError, match="go together"):
        initialize("127.0.0.1:1234", None, None)
    with pytest.raises(ConfigError, match="HOST:PORT"):
        initialize("127.0.0.1", 2, 0)
    with pytest.raises(ConfigError, match="--process-id"):
        initialize("127.0.0.1:1234", 2, 2)
    with pytest.raises(ConfigError, match="--num-processes"):
        initialize("127.0.0.1:1234", 0, 0)


def test_command_line_names_the_bad_device_count(tmp_path, capsys):
    from mpcpearl_jax.cli.train import main

    argv = ["--preset", "smoke", "--seeds", "4", "--devices", "3", "--out", str(tmp_path / "r")]
    assert main("restaurant", argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ExperimentConfig.devices" in err[0], err
