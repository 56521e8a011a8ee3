"""The exported policy (`export_policy`, `load_exported`): the same actions and z as
`load_policy`, from a process that cannot import flax or this package's networks; the committed
exports are those of the committed policies; bad files and inputs are one-line errors."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mpcpearl_jax.deploy.exported as exported_module
from mpcpearl_jax.deploy.adapter import Adapter, Frame, Scene
from mpcpearl_jax.deploy.export import export_policy
from mpcpearl_jax.deploy.exported import ExportError, load_exported, sidecar_path
from mpcpearl_jax.deploy.policy import load_policy
from mpcpearl_jax.envs import make_env, make_tasks

ROOT = Path(__file__).resolve().parents[1]
HEADLINE = ROOT / "results/restaurant/mpc-pearl-eps0.2"
COMMITTED = [
    "restaurant/mpc-pearl-eps0.2",
    "restaurant/pearl",
    "restaurant/mpc-sac",
    "sidewalk/mpc-pearl-eps0.2",
]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = export_policy(HEADLINE, tmp_path_factory.mktemp("export") / "policy.export")
    return out


def _inputs(policy, batch=33, rows=37, seed=0):
    k = jax.random.split(jax.random.PRNGKey(seed), 4)
    obs = jax.random.uniform(k[0], (batch, policy.obs_dim), minval=-1, maxval=1)
    z = jax.random.normal(k[1], (batch, policy.latent_dim))
    context = jax.random.normal(k[2], (rows, policy.context_dim))
    mask = (jnp.arange(rows) < rows - 5).astype(jnp.float32)
    return obs, z, context, mask


def test_exported_act_and_infer_z_equal_load_policy(exported):
    policy, ex = load_policy(HEADLINE), load_exported(exported)
    act, infer_z = policy.jit()
    for batch, rows in ((1, 1), (7, 80), (33, 37)):  # batch and context length are symbolic
        obs, z, context, mask = _inputs(policy, batch, rows)
        np.testing.assert_allclose(ex.act(obs, z), act(obs, z), rtol=0, atol=1e-6)
        np.testing.assert_allclose(ex.infer_z(context, mask), infer_z(context, mask), atol=1e-6)
        key = jax.random.PRNGKey(batch)
        np.testing.assert_allclose(
            ex.infer_z(context, mask, key), infer_z(context, mask, key), rtol=0, atol=1e-6
        )
    np.testing.assert_allclose(ex.act(obs[0], z[0]), act(obs[:1], z[:1])[0], atol=1e-6)
    z_all = jnp.broadcast_to(infer_z(context), (obs.shape[0], policy.latent_dim))
    np.testing.assert_allclose(ex(obs, context), act(obs, z_all), rtol=0, atol=1e-6)
    jact, jinfer = ex.jit()
    np.testing.assert_allclose(jact(obs, z), ex.act(obs, z), atol=1e-6)
    np.testing.assert_allclose(jinfer(context, mask), ex.infer_z(context, mask), atol=1e-6)


RUNNER = textwrap.dedent(
    """
    import importlib.abc, importlib.util, json, sys
    BLOCKED = ("flax", "mpcpearl_jax", "distrax", "optax", "orbax")

    class Block(importlib.abc.MetaPathFinder):  # before every other finder: these cannot load
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"{name} is blocked in this process")

    sys.meta_path.insert(0, Block())
    import numpy as np
    reader, export_file, inputs, out = sys.argv[1:5]
    spec = importlib.util.spec_from_file_location("policy_reader", reader)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    import jax
    policy = mod.load_exported(export_file)
    d = np.load(inputs)
    act = policy.act(d["obs"], d["z"])
    z_mean = policy.infer_z(d["context"], d["mask"])
    z_key = policy.infer_z(d["context"], d["mask"], jax.random.PRNGKey(7))
    np.savez(out, act=act, z_mean=z_mean, z_key=z_key)
    loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
    print(json.dumps({"loaded": loaded, "label": policy.meta["label"]}))
    """
)


def test_exported_policy_runs_where_flax_and_the_project_cannot_be_imported(exported, tmp_path):
    policy = load_policy(HEADLINE)
    obs, z, context, mask = _inputs(policy)
    np.savez(tmp_path / "in.npz", obs=obs, z=z, context=context, mask=mask)
    script = tmp_path / "run.py"
    script.write_text(RUNNER)
    reader = tmp_path / "policy_reader.py"  # the reader as one copied file
    reader.write_text(Path(exported_module.__file__).read_text())
    args = [str(reader), str(exported), str(tmp_path / "in.npz"), str(tmp_path / "out.npz")]
    proc = subprocess.run(
        [sys.executable, "-I", str(script), *args],  # -I: no PYTHONPATH, no current folder
        capture_output=True,
        text=True,
        timeout=300,
        env={"JAX_PLATFORMS": "cpu"},
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["loaded"] == [] and report["label"] == "MPC-PEARL 0.2"
    got = np.load(tmp_path / "out.npz")
    act, infer_z = policy.jit()
    np.testing.assert_allclose(got["act"], act(obs, z), rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["z_mean"], infer_z(context, mask), rtol=0, atol=1e-6)
    want = infer_z(context, mask, jax.random.PRNGKey(7))
    np.testing.assert_allclose(got["z_key"], want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("run", COMMITTED)
def test_committed_exports_are_those_of_the_committed_policies(run):
    run_dir = ROOT / "results" / run
    ex = load_exported(run_dir / "policy.export")
    meta = ex.meta
    for key, name in (("config_sha256", "config.json"), ("policy_sha256", "policy.msgpack")):
        assert meta[key] == hashlib.sha256((run_dir / name).read_bytes()).hexdigest()
    results = json.loads((run_dir / "results.json").read_text())
    assert meta["results"]["test_adapt"]["SR"] == results["test_adapt"]["SR"]
    policy = load_policy(run_dir)
    assert (ex.obs_dim, ex.latent_dim, ex.context_dim) == (
        policy.obs_dim,
        policy.latent_dim,
        policy.context_dim,
    )
    assert ex.t_update == policy.config.train.t_update
    obs, z, context, mask = _inputs(policy, seed=3)
    act, infer_z = policy.jit()
    np.testing.assert_allclose(ex.act(obs, z), act(obs, z), rtol=0, atol=1e-6)
    np.testing.assert_allclose(ex.infer_z(context, mask), infer_z(context, mask), atol=1e-6)
    assert (run_dir / "policy.export").stat().st_size < 1_000_000


@pytest.mark.slow  # (~12 s)
def test_adapter_on_the_exported_policy_acts_as_on_the_loaded_one(exported):
    policy, ex = load_policy(HEADLINE), load_exported(exported)
    cfg = policy.config
    env = make_env(cfg.env, **cfg.env_overrides)
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks(cfg.env, "test", config=env.config))
    a_loaded, a_exported = Adapter(policy), Adapter(ex)
    assert a_loaded.layout == a_exported.layout and a_exported.t_update == 5
    scene, key = Scene.from_task(task), jax.random.PRNGKey(4)
    s1, s2 = a_loaded.init(scene, key), a_exported.init(scene, key)
    _, state = env.reset(key, task)
    frame = Frame.start(state.pose, task.human_pos[0], task.human_mask[0])
    step = jax.jit(env.step)
    for t in range(30):
        action = a_loaded.act(s1, frame)
        np.testing.assert_allclose(a_exported.act(s2, frame), action, atol=1e-5)
        _, state, *_ = step(key, state, action, task)
        nxt = frame.advance(state.pose, task.human_pos[t + 1], task.human_mask[t + 1])
        s1, s2 = a_loaded.add(s1, frame, action, nxt), a_exported.add(s2, frame, action, nxt)
        frame = nxt
    np.testing.assert_allclose(a_exported.z(s2), a_loaded.z(s1), atol=1e-5)


# ------------------------------------------------------------------ errors
def _copy(exported: Path, tmp_path: Path) -> tuple[Path, Path, dict]:
    out = tmp_path / exported.name
    out.write_bytes(exported.read_bytes())
    side = sidecar_path(out)
    meta = json.loads(sidecar_path(exported).read_text())
    side.write_text(json.dumps(meta))
    return out, side, meta


def test_newer_format_and_mismatched_sidecar_are_clear_errors(exported, tmp_path):
    out, side, meta = _copy(exported, tmp_path)
    load_exported(out)  # the copy loads
    cases = [
        ({**meta, "format_version": 2}, r"format version 2 is newer than this reader \(1\)"),
        ({**meta, "format": "something else"}, "not an mpcpearl_jax policy export"),
        (
            {**meta, "observation": {**meta["observation"], "dim": 61}},
            r"observation\.dim 61 does not match the exported functions \(62\)",
        ),
        (
            {**meta, "functions": {**meta["functions"], "act": {"sha256": "0" * 64}}},
            "does not match policy.export",
        ),
    ]
    for bad, match in cases:
        side.write_text(json.dumps(bad))
        with pytest.raises(ExportError, match=match) as e:
            load_exported(out)
        assert "\n" not in str(e.value) and str(side.name) in str(e.value)
    side.unlink()
    with pytest.raises(ExportError, match=r"policy\.export\.json: missing"):
        load_exported(out)
    # a newer format inside the export file itself
    side.write_text(json.dumps(meta))
    with zipfile.ZipFile(out) as z:
        members = {n: z.read(n) for n in z.namelist()}
    members["manifest.json"] = json.dumps(
        {**json.loads(members["manifest.json"]), "format_version": 3}
    ).encode()
    with zipfile.ZipFile(out, "w") as z:
        for n, data in members.items():
            z.writestr(n, data)
    with pytest.raises(ExportError, match="format version 3 is newer"):
        load_exported(out)
    out.write_bytes(b"not a zip")
    with pytest.raises(ExportError, match="not a readable policy export"):
        load_exported(out)
    with pytest.raises(ExportError, match="no such export file"):
        load_exported(tmp_path / "nothing.export")


def test_bad_inputs_name_the_argument(exported):
    ex = load_exported(exported)
    with pytest.raises(ValueError, match=r"^obs: expected shape \[62\] or \[B, 62\], got \[61\]"):
        ex.act(jnp.zeros(61), jnp.zeros(10))
    with pytest.raises(ValueError, match=r"^z: expected shape \[3, 10\]"):
        ex.act(jnp.zeros((3, 62)), jnp.zeros((2, 10)))
    with pytest.raises(ValueError, match=r"^obs: contains NaN or inf"):
        ex.act(jnp.full(62, jnp.nan), jnp.zeros(10))
    with pytest.raises(ValueError, match=r"^context: expected shape \[C, 127\]"):
        ex.infer_z(jnp.zeros((4, 126)))
    with pytest.raises(ValueError, match=r"^mask: expected shape \[4\]"):
        ex.infer_z(jnp.zeros((4, 127)), jnp.ones(5))


def test_command_line(exported, tmp_path, capsys):
    from experiments import export as cli

    out = tmp_path / "cli" / "policy.export"
    assert cli.main([str(HEADLINE), "--out", str(out), "--platforms", "cpu"]) == 0
    assert "MPC-PEARL 0.2" in capsys.readouterr().out
    assert load_exported(out).meta["platforms"] == ["cpu"]
    assert cli.main([str(tmp_path / "nowhere")]) == 2
    assert "no such directory" in capsys.readouterr().err
    assert cli.main([str(HEADLINE), "--out", str(out), "--seed-index", "3"]) == 2
    assert "seed_index 3 out of range" in capsys.readouterr().err


def test_export_is_reproducible_and_names_no_file_of_this_machine(exported, tmp_path):
    again = export_policy(HEADLINE, tmp_path / "again.export")
    assert again.read_bytes() == exported.read_bytes()
    with zipfile.ZipFile(again) as z:
        for name in z.namelist():
            data = z.read(name)
            assert b".py" not in data and str(ROOT).encode() not in data, name
    assert str(ROOT) not in sidecar_path(again).read_text()


def test_sidecar_fields_are_checked_by_name(exported, tmp_path):
    """Every sidecar field the reader uses is checked on load, with one line naming the file and
    the field (a t_update of "five" used to fail later in int() naming nothing)."""
    out, side, meta = _copy(exported, tmp_path)
    cases = [
        ({**meta, "t_update": "five"}, "field t_update must be a positive integer, got 'five'"),
        ({**meta, "t_update": 0}, "field t_update must be a positive integer"),
        ({**meta, "latent_dim": True}, "field latent_dim must be a positive integer"),
        ({k: v for k, v in meta.items() if k != "t_update"}, "field t_update is missing"),
        ({**meta, "context": {}}, "field context.dim is missing"),
        ({**meta, "functions": {"act": {"sha256": 5}}}, "field functions.act.sha256 must be"),
        ({**meta, "policy_sha256": "abc"}, "field policy_sha256 must be a SHA-256"),
    ]
    for bad, match in cases:
        side.write_text(json.dumps(bad))
        with pytest.raises(ExportError, match=match) as e:
            load_exported(out)
        assert "\n" not in str(e.value) and side.name in str(e.value)


def test_an_export_beside_its_run_detects_a_changed_policy_or_config(exported, tmp_path):
    """Exported, then trained further (policy.msgpack replaced), the export beside the run is
    stale and says so; an edited t_update (a valid number, but not the run's) is refused too.
    Copied away from the run, the same files load."""
    run = tmp_path / "run"
    run.mkdir()
    for name in ("config.json", "network.json", "policy.msgpack"):
        (run / name).write_bytes((HEADLINE / name).read_bytes())
    out, side, meta = _copy(exported, run)
    load_exported(run)  # made from these very files
    policy = run / "policy.msgpack"
    policy.write_bytes(policy.read_bytes() + b"\0")  # a newer policy after --resume
    with pytest.raises(ExportError, match=r"stale: .*policy\.msgpack changed") as e:
        load_exported(run)
    assert "\n" not in str(e.value)
    policy.write_bytes((HEADLINE / "policy.msgpack").read_bytes())
    side.write_text(json.dumps({**meta, "t_update": 7}))  # within the episode, not the run's 5
    with pytest.raises(ExportError, match=r"field t_update 7 differs from the run's"):
        load_exported(run)
    config = run / "config.json"
    side.write_text(json.dumps(meta))
    config.write_text(config.read_text().replace('"t_update": 5', '"t_update": 6'))
    with pytest.raises(ExportError, match=r"stale: .*config\.json changed"):
        load_exported(run)
    away = tmp_path / "robot"
    away.mkdir()
    (away / out.name).write_bytes(out.read_bytes())
    (away / side.name).write_text(json.dumps(meta))
    assert load_exported(away).t_update == meta["t_update"]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def test_export_never_writes_over_a_run_record(tmp_path, capsys):
    """`experiments.export RUN --out RUN/policy.msgpack` used to replace the trained policy by
    the zip, and `--out RUN/results` results.json by the sidecar: both are refused with one
    line and the run folder stays byte-identical; so is any other file that is not an export."""
    from experiments import export as cli

    run = tmp_path / "run"
    run.mkdir()
    for name in ("config.json", "network.json", "policy.msgpack", "results.json"):
        (run / name).write_bytes((HEADLINE / name).read_bytes())
    (run / "notes.txt").write_text("mine")
    before = _snapshot(run)
    for out, what in (
        (run / "policy.msgpack", "policy.msgpack: an export may not take the name"),
        (run / "results", "results.json: an export may not take the name"),
        (run / "notes.txt", "notes.txt: exists and is not a policy export"),
    ):
        assert cli.main([str(run), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert what in err and err.count("\n") == 1, err
        assert _snapshot(run) == before
    # an earlier export is replaced (exporting again is what the option is for)
    assert cli.main([str(run), "--platforms", "cpu"]) == 0
    assert cli.main([str(run), "--platforms", "cpu"]) == 0
    assert {k: v for k, v in _snapshot(run).items() if "export" not in k} == before


def test_platforms_are_checked_before_anything_is_written(tmp_path, capsys):
    from experiments import export as cli

    out = tmp_path / "x" / "policy.export"
    assert cli.main([str(HEADLINE), "--out", str(out), "--platforms", "tpu9"]) == 2
    assert "unknown ['tpu9']" in capsys.readouterr().err and not out.parent.exists()
    # an export for another backend is written, checked as far as this machine can, and rc 0
    other = "cuda" if jax.default_backend() == "cpu" else "cpu"
    assert cli.main([str(HEADLINE), "--out", str(out), "--platforms", other]) == 0
    assert f"not for this machine's {jax.default_backend()}" in capsys.readouterr().out
    assert json.loads(sidecar_path(out).read_text())["platforms"] == [other]


def test_an_empty_batch_gives_an_empty_batch_of_actions(exported):
    """`act` takes any batch size, none included: B = 0 gives [0, 2] (it raised JAX's internal
    "Expected value >= 1 for dimension variable 'b'"), eagerly and jitted."""
    ex = load_exported(exported)
    obs, z = np.zeros((0, ex.obs_dim)), np.zeros((0, ex.latent_dim))
    assert ex.act(obs, z).shape == (0, 2)
    assert ex.jit()[0](obs, z).shape == (0, 2)
    assert ex(obs, np.zeros((3, ex.context_dim))).shape == (0, 2)


def test_a_sidecar_with_edited_run_hashes_is_refused_away_from_its_run(exported, tmp_path):
    """An export copied away from its run cannot compare the sidecar's policy_sha256 and
    config_sha256 with the run's files; the export records them too, so an edited one is a
    one-line error naming the field (it loaded without a word), as is one that is not hex."""
    out, side, meta = _copy(exported, tmp_path)
    load_exported(out)
    for key in ("policy_sha256", "config_sha256"):
        side.write_text(json.dumps({**meta, key: "0" * 64}))
        with pytest.raises(ExportError, match=f"field {key} differs from the one policy.export"):
            load_exported(out)
    side.write_text(json.dumps({**meta, "policy_sha256": "z" * 64}))
    with pytest.raises(ExportError, match="field policy_sha256 must be a SHA-256"):
        load_exported(out)
