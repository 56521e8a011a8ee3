"""Export a trained policy as a portable artifact: `export_policy(run_dir, out)`.

The policy's deterministic `act` (batch size symbolic) and the encoder's `infer_z` (number of
context rows symbolic) are serialized with `jax.export` (StableHLO, the parameters folded in) into
`out` (default `<run_dir>/policy.export`), with a JSON sidecar `out.json` describing how to feed
them. `exported.load_exported` runs them with jax alone (see `mpcpearl_jax.deploy.exported`).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from jax import export as jax_export

from mpcpearl_jax import __version__
from mpcpearl_jax.deploy.adapter import Layout
from mpcpearl_jax.deploy.exported import (
    FORMAT,
    FORMAT_VERSION,
    FUNCTIONS,
    MANIFEST,
    ExportError,
    sha256,
    sidecar_path,
)
from mpcpearl_jax.deploy.policy import load_policy
from mpcpearl_jax.envs import observation
from mpcpearl_jax.envs.dynamics import DELTA_MAX
from mpcpearl_jax.evaluation.metrics import METRIC_NAMES
from mpcpearl_jax.evaluation.report import run_label
from mpcpearl_jax.runfolder import CONFIG_FILE, POLICY_FILE, RUN_RECORDS, atomic_write
from mpcpearl_jax.validate import unwritable_folder

EXPORT_FILE = "policy.export"
DEFAULT_PLATFORMS = ("cpu", "cuda")
PLATFORMS = ("cpu", "cuda", "rocm", "tpu")  # what jax.export lowers for
RESULT_KEYS = ("test_adapt", "test_online", "ood_adapt")


def _functions(policy) -> dict[str, Any]:
    """The two functions to serialize, closed over the policy's parameters."""
    nets, params = policy.nets, policy.params

    def act(obs, z):  # [B, O], [B, L] -> [B, 2]: tanh of the Gaussian's mean
        return nets.act(params["policy"], obs, z, None)

    def infer_z(context, mask, noise):  # [C, D], [C], [L] -> [L]: mean + sqrt(var) * noise
        if not nets.cfg.use_context:  # plain SAC: z = 0 (`Networks.posterior_sample`)
            return jnp.zeros_like(noise)
        _, mean, var = nets.posterior_sample(params["encoder"], context, None, mask)
        return mean + jnp.sqrt(var) * noise

    return {"act": act, "infer_z": infer_z}


def _serialize(policy, platforms: Sequence[str]) -> dict[str, bytes]:
    o, lat, d = policy.obs_dim, policy.latent_dim, policy.context_dim
    b, c = jax_export.symbolic_shape("b, c")
    f32 = jnp.float32
    specs = {
        "act": (jax.ShapeDtypeStruct((b, o), f32), jax.ShapeDtypeStruct((b, lat), f32)),
        "infer_z": (
            jax.ShapeDtypeStruct((c, d), f32),
            jax.ShapeDtypeStruct((c,), f32),
            jax.ShapeDtypeStruct((lat,), f32),
        ),
    }
    fns = _functions(policy)
    out = {}
    with _no_source_locations():
        for name in FUNCTIONS:
            exp = jax_export.export(jax.jit(fns[name]), platforms=tuple(platforms))(*specs[name])
            out[name] = bytes(exp.serialize())
    return out


@contextlib.contextmanager
def _no_source_locations():
    """Lower without Python source locations: the serialized program names no file of the
    machine it was exported on, and the same policy exports to the same bytes."""
    names = ("jax_traceback_in_locations_limit", "jax_include_full_tracebacks_in_locations")
    saved = {n: getattr(jax.config, n) for n in names}
    jax.config.update(names[0], 0)
    jax.config.update(names[1], True)
    try:
        yield
    finally:
        for n, v in saved.items():
            jax.config.update(n, v)


def _file_sha256(path: Path) -> str | None:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None


def _results(run_dir: Path) -> dict[str, Any]:
    """The run's headline metrics (results.json), mean over seeds."""
    path = run_dir / "results.json"
    if not path.is_file():
        return {}
    raw = json.loads(path.read_text())
    out = {}
    for k in RESULT_KEYS:
        if isinstance(raw.get(k), dict):
            out[k] = {m: raw[k][m] for m in METRIC_NAMES if m in raw[k]}
    return out


def sidecar(policy, run_dir: Path, seed_index: int, blobs: dict[str, bytes], platforms) -> dict:
    """The sidecar's content (see `mpcpearl_jax.deploy.exported`)."""
    cfg = policy.config
    layout = Layout.of(policy)
    nav = layout.config
    o, lat, d = policy.obs_dim, policy.latent_dim, policy.context_dim
    env_config = {k: list(v) if isinstance(v, tuple) else v for k, v in vars(nav).items()}
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "written_by": f"mpcpearl_jax {__version__}, jax {jax.__version__}",
        "platforms": list(platforms),
        "run": run_dir.name,
        "seed_index": seed_index,
        "label": run_label(cfg),
        "config_sha256": _file_sha256(run_dir / CONFIG_FILE),
        "policy_sha256": _file_sha256(run_dir / POLICY_FILE),
        "results": _results(run_dir),
        "env": cfg.env,
        "env_config": env_config,
        "observation": {
            "dim": o,
            "num_people": layout.num_people,
            "num_static": layout.num_static,
            "options": {k: getattr(nav, k) for k in observation.OPTIONS},
            "frame": (
                f"metres and radians in the training arena x in [{nav.arena_lo[0]:g}, "
                f"{nav.arena_hi[0]:g}], y in [{nav.arena_lo[1]:g}, {nav.arena_hi[1]:g}]"
            ),
            "people_order": "nearest first" if nav.observe_sorted else "by identity (row)",
            "layout": layout.parts(),
            "builder": "mpcpearl_jax.deploy.adapter.observe (equal to the env's observation)",
        },
        "action": {
            "dim": 2,
            "low": [-1.0, -1.0],
            "high": [1.0, 1.0],
            "deterministic": "tanh of the Gaussian policy's mean",
            "physical": [
                {
                    "name": "v",
                    "unit": "m/s",
                    "low": 0.0,
                    "high": nav.v_max,
                    "from_action": "v = (a[0] + 1) / 2 * v_max",
                },
                {
                    "name": "delta",
                    "unit": "rad",
                    "low": -float(DELTA_MAX),
                    "high": float(DELTA_MAX),
                    "from_action": "delta = a[1] * pi / 2",
                },
            ],
            "robot": (
                f"kinematic bicycle (method §1), wheelbase {nav.wheelbase:g} m, step dt "
                f"{nav.dt:g} s; speed 0 within {nav.robot_radius:g} m of the goal"
            ),
        },
        "latent_dim": lat,
        "context": {
            "dim": d,
            "row": f"(s [{o}], a [2], r [1], s' [{o}]), r the unscaled reward of eq. (2)",
            "builder": "mpcpearl_jax.deploy.adapter.Adapter",
        },
        "t_update": cfg.train.t_update,
        "functions": {
            "act": {
                "inputs": [f"obs float32 [B, {o}]", f"z float32 [B, {lat}]"],
                "output": "action float32 [B, 2]",
                "sha256": sha256(blobs["act"]),
            },
            "infer_z": {
                "inputs": [
                    f"context float32 [C, {d}]",
                    "mask float32 [C]",
                    f"noise float32 [{lat}]",
                ],
                "output": f"z float32 [{lat}] = posterior mean + sqrt(posterior var) * noise",
                "sha256": sha256(blobs["infer_z"]),
            },
        },
        "reader": "mpcpearl_jax.deploy.exported.load_exported (one file; needs jax only)",
    }


def runs_here(platforms: Sequence[str]) -> bool:
    """Whether an export for `platforms` loads on this machine's default backend."""
    backend = jax.default_backend()
    return bool({"gpu": {"cuda", "rocm"}}.get(backend, {backend}) & set(platforms))


def _is_export(path: Path) -> bool:
    """Whether `path` is a policy export file or sidecar (this module wrote it)."""
    try:
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as z:
                return json.loads(z.read(MANIFEST)).get("format") == FORMAT
        return json.loads(path.read_text()).get("format") == FORMAT
    except (OSError, KeyError, ValueError, AttributeError, zipfile.BadZipFile):
        return False


def check_target(out: Path) -> None:
    """ExportError naming the file when writing an export to `out` (and its sidecar beside it)
    would replace a run's own record (policy.msgpack, results.json, ...) or any existing file
    that is not an earlier export."""
    for path in (out, sidecar_path(out)):
        if path.name in RUN_RECORDS:  # a run's own record (runfolder.RUN_RECORDS)
            raise ExportError(
                f"{path}: an export may not take the name of a run's own record; choose "
                "another --out (default RUN/policy.export)"
            )
        if path.is_dir() or (path.exists() and not _is_export(path)):
            raise ExportError(f"{path}: exists and is not a policy export; choose another --out")
    check_folder(out.parent)


def check_folder(folder: Path) -> None:
    """Create the export's folder and prove it writable (a probe file written and removed),
    before the export is built; ExportError naming the folder and the cause otherwise (a
    read-only folder, a file where a folder should be)."""
    why = unwritable_folder(folder)
    if why is not None:
        msg = f"{folder}: cannot write the export there ({why}); choose another --out"
        raise ExportError(msg)


def export_policy(
    run_dir: str | Path,
    out: str | Path | None = None,
    seed_index: int = 0,
    platforms: Sequence[str] = DEFAULT_PLATFORMS,
) -> Path:
    """Export the policy of seed `seed_index` of a run (see module doc). Returns the export
    file's path (`out` a folder, or a path ending in "/": policy.export in it); the sidecar is
    that path with `.json` appended. Both are written atomically,
    never over a run's own records or a file that is not an earlier export (`check_target`);
    ExportError naming an unknown platform or a refused file before anything is written."""
    run_dir = Path(run_dir)
    unknown = [p for p in platforms if p not in PLATFORMS]
    if unknown or not platforms:
        raise ExportError(
            f"platforms {list(platforms)}: unknown {unknown or 'none given'}; "
            f"choose from {', '.join(PLATFORMS)}"
        )
    folder = isinstance(out, str) and out.endswith(("/", os.sep))  # "DIR/": a folder, new or not
    out = Path(out) if out is not None else run_dir / EXPORT_FILE
    if folder or out.is_dir():
        out = out / EXPORT_FILE
    check_target(out)
    policy = load_policy(run_dir, seed_index)
    blobs = _serialize(policy, platforms)
    meta = sidecar(policy, run_dir, seed_index, blobs, platforms)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        # the run files' SHA-256 in the export too: a sidecar edited away from its run is found
        shas = {k: meta[k] for k in ("policy_sha256", "config_sha256")}
        manifest = {"format": FORMAT, "format_version": FORMAT_VERSION, **shas}
        _add(z, MANIFEST, json.dumps(manifest, indent=2).encode())
        for name in FUNCTIONS:
            _add(z, f"{name}.jaxexport", blobs[name])
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, buf.getvalue())
    atomic_write(sidecar_path(out), json.dumps(meta, indent=2) + "\n")
    return out


def _add(z: zipfile.ZipFile, name: str, data: bytes) -> None:
    """A member with a fixed timestamp, so that the same policy exports to the same bytes."""
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_DEFLATED
    z.writestr(info, data)
