"""`load_policy` needs no environment: network.json (or, for older runs, the parameter shapes)
gives the network dimensions, so a sidewalk run loads after its data file is gone."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mpcpearl_jax.runfolder as runfolder
import mpcpearl_jax.training.checkpoint as checkpoint
from mpcpearl_jax.deploy.policy import load_policy
from mpcpearl_jax.runfolder import NETWORK_FILE, save_network
from mpcpearl_jax.training.checkpoint import CheckpointError

ROOT = Path(__file__).resolve().parents[1]
SIDEWALK_RUN = ROOT / "results" / "sidewalk" / "ablation" / "cpu-10min"  # no network.json
RESTAURANT_RUN = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2"


def _copy_run(src: Path, dst: Path, data: str | None = None) -> Path:
    dst.mkdir(parents=True)
    for name in ("config.json", "policy.msgpack"):
        shutil.copy(src / name, dst / name)
    if data is not None:
        cfg = json.loads((dst / "config.json").read_text())
        cfg["data"] = data
        (dst / "config.json").write_text(json.dumps(cfg))
    return dst


def _same_policy(a, b) -> None:
    assert a.nets.spec() == b.nets.spec()
    obs = jax.random.uniform(jax.random.PRNGKey(0), (4, a.obs_dim), minval=-1, maxval=1)
    ctx = jax.random.normal(jax.random.PRNGKey(1), (6, a.context_dim))
    np.testing.assert_array_equal(np.asarray(a(obs, ctx)), np.asarray(b(obs, ctx)))


def test_checkpoint_module_does_not_import_envs():
    for module in (checkpoint, runfolder):
        assert "mpcpearl_jax.envs" not in Path(module.__file__).read_text()


def test_loading_a_policy_needs_no_orbax():
    """deploy reads a run folder through `runfolder`, not the training package: loading a
    policy imports no orbax (the checkpoints' library)."""
    code = (
        "import sys; import mpcpearl_jax.deploy.policy, mpcpearl_jax.deploy.export; "
        "print([m for m in sys.modules if m.startswith(('orbax', 'mpcpearl_jax.training'))])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_sidewalk_run_loads_after_its_data_file_is_gone(tmp_path):
    gone = tmp_path / "crowds_zara01.txt"  # the run's data file, deleted
    gone.write_text("0 1 0.0 0.0\n")
    run = _copy_run(SIDEWALK_RUN, tmp_path / "run", data=str(gone))
    gone.unlink()
    pol = load_policy(run)
    assert (pol.obs_dim, pol.context_dim, pol.latent_dim) == (13, 29, 10)
    _same_policy(pol, load_policy(SIDEWALK_RUN))
    a = pol(jnp.zeros((3, 13)), jnp.zeros((5, 29)))
    assert a.shape == (3, 2) and bool(jnp.all(jnp.isfinite(a)))


@pytest.mark.parametrize("src", [SIDEWALK_RUN, RESTAURANT_RUN], ids=["sidewalk", "restaurant"])
def test_network_json_and_shapes_give_the_same_networks(tmp_path, src):
    old = load_policy(src)  # committed before network.json existed: dims from the shapes
    run = _copy_run(src, tmp_path / "run")
    save_network(run, old.nets)
    spec = json.loads((run / NETWORK_FILE).read_text())
    assert spec["obs_dim"] == old.obs_dim and spec["context_dim"] == 2 * old.obs_dim + 3
    _same_policy(load_policy(run), old)


def test_network_json_that_does_not_match_the_policy_file_is_an_error(tmp_path):
    run = _copy_run(SIDEWALK_RUN, tmp_path / "run")
    spec = load_policy(run).nets.spec()
    (run / NETWORK_FILE).write_text(json.dumps({**spec, "hidden": [64, 64]}))
    with pytest.raises(CheckpointError, match="different network size"):
        load_policy(run)
    (run / NETWORK_FILE).write_text(json.dumps({**spec, "context_dim": 30}))
    with pytest.raises(CheckpointError, match="context_dim"):
        load_policy(run)
