"""Run an exported policy with jax alone: `load_exported(path)`.

`mpcpearl_jax.export_policy` (or `python -m experiments.export RUN_DIR`) writes two files:

  policy.export        a zip of the policy's `act` and the encoder's `infer_z`, each serialized
                       with `jax.export` (StableHLO, parameters included), and a manifest
  policy.export.json   the sidecar: format version, observation layout and options, action
                       bounds and units, latent and context sizes, t_update, the SHA-256 of each
                       serialized function, the run's config hash and results

This module imports nothing but the standard library and jax (no flax, no networks, no other
part of this package), so it can be copied next to the two files onto a robot and imported on its
own. The policy is deterministic: `act` returns tanh of the Gaussian's mean.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from jax import export as jax_export

FORMAT = "mpcpearl_jax policy export"
FORMAT_VERSION = 1  # the newest format this reader understands
MANIFEST = "manifest.json"
SIDECAR_SUFFIX = ".json"
FUNCTIONS = ("act", "infer_z")
_PLATFORMS = {"gpu": ("cuda", "rocm")}  # jax's backend name -> jax.export's platform names


class ExportError(ValueError):
    """An exported policy that cannot be used: missing, from a newer format, or a sidecar that
    does not match its export file. The message names the file."""


def sidecar_path(path: str | Path) -> Path:
    """The sidecar of an export file: the same name with `.json` appended."""
    path = Path(path)
    return path.with_name(path.name + SIDECAR_SUFFIX)


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def check_format(meta: dict, where: Path) -> None:
    """ExportError naming `where` unless `meta` is this format, at a version this reader knows."""
    if meta.get("format") != FORMAT:
        raise ExportError(
            f"{where}: not an mpcpearl_jax policy export (format {meta.get('format')!r})"
        )
    version = meta.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise ExportError(f"{where}: invalid format_version {version!r}")
    if version > FORMAT_VERSION:
        raise ExportError(
            f"{where}: format version {version} is newer than this reader ({FORMAT_VERSION}); "
            "update mpcpearl_jax (or its exported.py) to load it"
        )


def _read_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise ExportError(f"{path}: missing ({what})")
    try:
        out = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ExportError(f"{path}: not valid JSON ({e})") from e
    if not isinstance(out, dict):
        raise ExportError(f"{path}: expected a JSON object ({what})")
    return out


def _read_members(path: Path) -> tuple[dict, dict[str, bytes]]:
    if not path.is_file():
        raise ExportError(f"{path}: no such export file")
    try:
        with zipfile.ZipFile(path) as z:
            manifest = json.loads(z.read(MANIFEST))
            check_format(manifest, path)
            blobs = {name: z.read(f"{name}.jaxexport") for name in FUNCTIONS}
    except ExportError:
        raise
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError, OSError) as e:
        raise ExportError(f"{path}: not a readable policy export ({type(e).__name__}: {e})") from e
    return manifest, blobs


def _is_traced(x: Any) -> bool:
    return isinstance(x, jax.core.Tracer)


def _checked(name: str, x: Any, expected: str, ok: Callable[[tuple], bool]) -> Any:
    """x as a float32 array; ValueError naming `name` if its shape fails `ok`, or if a concrete
    x holds NaN or inf."""
    x = x if _is_traced(x) else jnp.asarray(x, jnp.float32)
    if not ok(tuple(x.shape)):
        raise ValueError(f"{name}: expected shape {expected}, got {list(x.shape)}")
    if not _is_traced(x) and not bool(jnp.all(jnp.isfinite(x))):
        raise ValueError(f"{name}: contains NaN or inf (expected finite values, shape {expected})")
    return x.astype(jnp.float32)


def check_key(key: Any, name: str = "key") -> Any:
    """`key` if it is None or a JAX PRNG key (`jax.random.key(seed)`, or the raw uint32 key of
    `jax.random.PRNGKey(seed)`); TypeError naming `name` otherwise (an int seed, a float array)."""
    if key is None:
        return None
    dtype, shape = getattr(key, "dtype", None), tuple(getattr(key, "shape", (None,)))
    if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key) and shape == ():
        return key
    if dtype == jnp.uint32 and len(shape) == 1 and shape[0] in (2, 4):
        return key
    got = (
        f"{type(key).__name__} {key!r}"
        if dtype is None
        else f"{dtype} array of shape {list(shape)}"
    )
    raise TypeError(
        f"{name}: expected a PRNG key (jax.random.key(seed) or jax.random.PRNGKey(seed)) or "
        f"None, got {got}"
    )


class ExportedPolicy:
    """A policy loaded from its export (see module doc). Mirrors `policy.LoadedPolicy`:

    act(obs [O] or [B, O], z [L] or [B, L]) -> action [2] or [B, 2] in [-1, 1] (tanh of the mean)
    infer_z(context [C, D], mask [C] | None, key=None) -> z [L] (posterior mean if no key, else a
      sample z = mean + sqrt(var) * N(0, I) drawn with `key`)
    __call__(obs, context, mask=None, key=None) -> action: z from the context, then act.

    Every method is jittable; concrete inputs are checked for shape and NaN / inf (ValueError
    naming the argument), traced ones for shape only. `meta` is the sidecar.
    """

    def __init__(self, meta: dict, act: jax_export.Exported, infer_z: jax_export.Exported):
        self.meta = meta
        self._act = act
        self._infer_z = infer_z

    @property
    def obs_dim(self) -> int:
        return int(self.meta["observation"]["dim"])

    @property
    def latent_dim(self) -> int:
        return int(self.meta["latent_dim"])

    @property
    def context_dim(self) -> int:
        return int(self.meta["context"]["dim"])

    @property
    def t_update(self) -> int:
        return int(self.meta["t_update"])

    def act(self, obs: Any, z: Any) -> Any:
        o, lat = self.obs_dim, self.latent_dim
        obs = _checked("obs", obs, f"[{o}] or [B, {o}]", lambda s: len(s) in (1, 2) and s[-1] == o)
        want = obs.shape[:-1] + (lat,)
        z = _checked("z", z, f"{list(want)} (the batch shape of obs)", lambda s: s == want)
        if obs.ndim == 1:
            return self._act.call(obs[None], z[None])[0]
        if obs.shape[0] == 0:  # the exported function's batch dimension starts at 1
            return jnp.zeros((0, self._act.out_avals[0].shape[-1]), jnp.float32)
        return self._act.call(obs, z)

    def infer_z(self, context: Any, mask: Any = None, key: Any = None) -> Any:
        d = self.context_dim
        expected = f"[C, {d}] (C >= 1 rows of (s, a, r, s'))"
        context = _checked(
            "context", context, expected, lambda s: len(s) == 2 and s[0] >= 1 and s[1] == d
        )
        c = context.shape[0]
        if mask is None:
            mask = jnp.ones((c,), jnp.float32)
        else:
            mask = _checked("mask", mask, f"[{c}] (one per context row)", lambda s: s == (c,))
        shape = (self.latent_dim,)
        key = check_key(key)
        noise = jnp.zeros(shape, jnp.float32) if key is None else jax.random.normal(key, shape)
        return self._infer_z.call(context, mask, noise)

    def __call__(self, obs: Any, context: Any, mask: Any = None, key: Any = None) -> Any:
        z = self.infer_z(context, mask, key)
        obs = jnp.asarray(obs) if not _is_traced(obs) else obs
        return self.act(obs, jnp.broadcast_to(z, obs.shape[:-1] + z.shape[-1:]))

    def jit(self) -> tuple[Callable, Callable]:
        """(jitted act, jitted infer_z): shapes checked once when traced, values not."""
        return jax.jit(self.act), jax.jit(self.infer_z)


def _check_signature(meta: dict, act: jax_export.Exported, infer_z: jax_export.Exported, where):
    """The sidecar's sizes against the serialized functions' input shapes."""
    o, lat, d = meta["observation"]["dim"], meta["latent_dim"], meta["context"]["dim"]
    got = {
        "observation.dim": act.in_avals[0].shape[-1],
        "latent_dim": act.in_avals[1].shape[-1],
        "context.dim": infer_z.in_avals[0].shape[-1],
    }
    for field, want in (("observation.dim", o), ("latent_dim", lat), ("context.dim", d)):
        if got[field] != want:
            raise ExportError(
                f"{where}: {field} {want} does not match the exported functions ({got[field]}); "
                "the sidecar belongs to another export"
            )


# sidecar fields this reader uses: dotted name -> (test, what it must be)
_POSITIVE_INT = (
    lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1,
    "a positive integer",
)
_SHA = (
    lambda v: isinstance(v, str) and len(v) == 64 and set(v) <= set("0123456789abcdef"),
    "a SHA-256 hex string",
)
SIDECAR_FIELDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "observation.dim": _POSITIVE_INT,
    "latent_dim": _POSITIVE_INT,
    "context.dim": _POSITIVE_INT,
    "t_update": _POSITIVE_INT,
    **{f"functions.{name}.sha256": _SHA for name in FUNCTIONS},
}


def check_sidecar(meta: dict, where: Path) -> None:
    """ExportError naming `where` and the field for the first sidecar field this reader uses
    that is missing or of the wrong type (and for a `policy_sha256` that is not a hash)."""
    for field, (ok, what) in SIDECAR_FIELDS.items():
        value: Any = meta
        for part in field.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        if value is None:
            raise ExportError(f"{where}: field {field} is missing")
        if not ok(value):
            raise ExportError(f"{where}: field {field} must be {what}, got {value!r}")
    if "policy_sha256" in meta and not _SHA[0](meta["policy_sha256"]):
        raise ExportError(f"{where}: field policy_sha256 must be {_SHA[1]}")
    env = meta.get("env_config")
    horizon = env.get("horizon") if isinstance(env, dict) else None
    if _POSITIVE_INT[0](horizon) and meta["t_update"] > horizon:  # z re-inferred within an episode
        raise ExportError(
            f"{where}: field t_update must be at most the episode length env_config.horizon "
            f"({horizon} steps), got {meta['t_update']!r}"
        )


def check_not_stale(meta: dict, path: Path) -> None:
    """An export beside its run's files must have been made from them: policy.msgpack and
    config.json with the SHA-256 the sidecar recorded (after training went on with `--resume`
    the export is stale), and the sidecar's t_update the run's. ExportError naming the file
    otherwise. An export copied away from its run (no such file beside it) is not checked."""
    for name, key in (("policy.msgpack", "policy_sha256"), ("config.json", "config_sha256")):
        beside, want = path.parent / name, meta.get(key)
        if want is not None and beside.is_file() and sha256(beside.read_bytes()) != want:
            raise ExportError(
                f"{path}: stale: {beside} changed since this export was made (its SHA-256 "
                f"differs from the sidecar's {key}); export again with python -m "
                f"experiments.export {path.parent}"
            )
    config = path.parent / "config.json"
    if meta.get("config_sha256") is not None and config.is_file():
        try:
            t_update = json.loads(config.read_text())["train"]["t_update"]
        except (json.JSONDecodeError, KeyError, TypeError):
            return
        if t_update != meta["t_update"]:
            raise ExportError(
                f"{sidecar_path(path)}: field t_update {meta['t_update']!r} differs from the "
                f"run's {config} ({t_update!r}); the sidecar was edited: export again"
            )


def load_exported(path: str | Path) -> ExportedPolicy:
    """The policy exported to `path` (a `policy.export` file, or the run directory holding one),
    with its sidecar `policy.export.json` beside it. ExportError naming the file if either is
    missing, from a newer format version, if they do not match, if a sidecar field is missing
    or of the wrong type (naming the field), or if the run's policy.msgpack beside the export
    has changed since it was made (a stale export)."""
    path = Path(path)
    if path.is_dir():
        path = path / "policy.export"
    if not path.is_file():
        raise ExportError(f"{path}: no such export file")
    side = sidecar_path(path)
    meta = _read_json(side, f"the sidecar of {path.name}")
    check_format(meta, side)
    check_sidecar(meta, side)
    manifest, blobs = _read_members(path)
    for key in ("policy_sha256", "config_sha256"):  # the export records them too (not older ones)
        if key in manifest and meta.get(key) != manifest[key]:
            raise ExportError(
                f"{side}: field {key} differs from the one {path.name} records; the sidecar was "
                "edited or belongs to another export: export again"
            )
    check_not_stale(meta, path)
    for name in FUNCTIONS:
        want = meta.get("functions", {}).get(name, {}).get("sha256")
        if want != sha256(blobs[name]):
            raise ExportError(
                f"{side}: does not match {path.name} (SHA-256 of {name} differs); the sidecar "
                "belongs to another export"
            )
    try:
        act, infer_z = (jax_export.deserialize(bytearray(blobs[n])) for n in FUNCTIONS)
    except Exception as e:  # jax raises several types for an unreadable or too new encoding
        raise ExportError(f"{path}: cannot deserialize ({type(e).__name__}: {e})") from e
    try:
        _check_signature(meta, act, infer_z, side)
    except (KeyError, TypeError) as e:
        raise ExportError(f"{side}: incomplete sidecar (missing {e})") from e
    backend = jax.default_backend()
    if not set(_PLATFORMS.get(backend, (backend,))) & set(act.platforms):
        raise ExportError(
            f"{path}: exported for {', '.join(act.platforms)}, not for this machine's {backend}; "
            "export again here or run on one of those"
        )
    return ExportedPolicy(meta, act, infer_z)


__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "ExportError",
    "ExportedPolicy",
    "check_format",
    "check_not_stale",
    "check_sidecar",
    "load_exported",
    "sidecar_path",
]
