"""The files of a run folder: their names, atomic writes, the metrics log and the config and
policy files (the layer every reader of a run folder shares: training writes them, evaluation,
GrBAL and deploy read them; orbax checkpoints stay with training, `training.checkpoint`).

A run directory holds:
  config.json         the ExperimentConfig (what `--resume` rebuilds from)
  network.json        the network dimensions and sizes (`Networks.spec`, as brax saves its
                      network config), written with config.json
  metrics.jsonl       one line per iteration, appended one whole line at a time
  checkpoints/<it>/   orbax checkpoints of the whole TrainState (`training.checkpoint`)
  policy.msgpack      policy + encoder parameters of every seed (flax serialization)
`mpcpearl_jax.deploy.policy.load_policy` reads config.json, network.json and policy.msgpack only.

Every file is written atomically (a temporary file renamed over the old one), so a process killed
at any moment leaves the previous version intact.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import serialization

from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.errors import CheckpointError
from mpcpearl_jax.pearl.networks import Networks

LOG_FILE = "metrics.jsonl"
CONFIG_FILE = "config.json"
POLICY_FILE = "policy.msgpack"
NETWORK_FILE = "network.json"
# a run folder's own records: no command writes over them but the run itself (an evaluation, an
# export, another run refuse a folder that holds them, unless told to replace the run)
RUN_RECORDS = (
    CONFIG_FILE,
    POLICY_FILE,
    NETWORK_FILE,
    "metrics.jsonl",
    "results.json",
    "curve.json",
    "curve-points.jsonl",
)


def atomic_write(path: Path, data: bytes | str) -> None:
    """Write `data` to `path` through a temporary file in the same folder and a rename: readers
    (and a later resume) see the old or the new content, never a torn file."""
    path = Path(path)
    raw = data.encode() if isinstance(data, str) else data
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:  # e.g. a full disk: name the file, not its temporary
        raise OSError(e.errno, e.strerror or str(e), str(path)) from e
    finally:
        if tmp.exists():
            tmp.unlink()


def strict_json(obj: Any, indent: int | None = 2) -> str:
    """JSON text without the non-standard NaN / Infinity tokens: a non-finite float is written
    as null, and a dict at the top level gets a `null_values` entry saying which fields were
    not finite and what they held (e.g. {"pooled.SR.se": "NaN"})."""
    nulls: dict[str, str] = {}

    def clean(x: Any, where: str) -> Any:
        if isinstance(x, dict):
            return {k: clean(v, f"{where}.{k}" if where else str(k)) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v, f"{where}[{i}]") for i, v in enumerate(x)]
        if isinstance(x, float) and not math.isfinite(x):
            nulls[where] = "NaN" if math.isnan(x) else ("Infinity" if x > 0 else "-Infinity")
            return None
        return x

    out = clean(obj, "")
    if nulls and isinstance(out, dict):
        out["null_values"] = {
            k: f"{v} (not a finite number; written as null)" for k, v in nulls.items()
        }
    return json.dumps(out, indent=indent, allow_nan=False)


def write_json(path: Path, obj: Any) -> None:
    """`strict_json(obj)` written atomically to `path` (results.json, curve.json)."""
    atomic_write(path, strict_json(obj))


def non_finite_leaves(tree: Any) -> list[str]:
    """Paths of the floating-point leaves of `tree` that hold NaN or inf."""
    bad = []
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        x = np.asarray(leaf)
        if np.issubdtype(x.dtype, np.floating) and not np.all(np.isfinite(x)):
            bad.append(jax.tree_util.keystr(path))
    return bad


def save_params(path: Path, params: Any) -> None:
    """Network parameters (flax msgpack) written atomically; CheckpointError naming the file if
    any of them is NaN or inf (a diverged network is never saved as a policy)."""
    bad = non_finite_leaves(params)
    if bad:
        raise CheckpointError(
            f"{path}: not saved: non-finite network parameters (NaN or inf in {len(bad)} "
            f"array(s), e.g. {bad[0]}); the run diverged, its last good checkpoint is kept"
        )
    atomic_write(path, serialization.to_bytes(params))


def save_config(run_dir: Path, cfg: Any) -> None:
    """config.json of any run (a config with `to_json`), written atomically."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write(run_dir / CONFIG_FILE, cfg.to_json())


def save_network(run_dir: Path, nets: Networks) -> None:
    """network.json: what `load_policy` rebuilds the networks from (`Networks.spec`)."""
    atomic_write(Path(run_dir) / NETWORK_FILE, json.dumps(nets.spec(), indent=2, sort_keys=True))


def load_config(run_dir: str | Path, resume: bool = False) -> ExperimentConfig:
    """The run's config.json. A run trained with an option since removed
    (`config.REMOVED_OPTIONS`) loads for evaluation with the option dropped; with `resume` it is
    refused, since continuing it would train without the option."""
    from mpcpearl_jax.config import removed_options_on

    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise CheckpointError(f"{path}: no config.json; is this a run directory?")
    try:
        raw = json.loads(path.read_text())
        if isinstance(raw, dict) and raw.get("method") == "grbal":
            raise CheckpointError(
                f"{run_dir}: a GrBAL run (a learned dynamics model planned with MPPI, not a "
                "policy): load_policy does not apply; python -m experiments.evaluate scores it "
                "with its own controller, and python -m experiments.grbal evaluates it when "
                "training ends (results.json)"
            )
        on = removed_options_on(raw) if isinstance(raw, dict) else []
        if resume and on:
            raise CheckpointError(
                f"{run_dir}: trained with {', '.join(on)}, option(s) since removed "
                "(docs/extensions.md, Removed options); the run can be evaluated, not resumed"
            )
        return ExperimentConfig.from_dict(raw)
    except (json.JSONDecodeError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: unreadable or invalid config ({e})") from e


def warn(msg: str) -> None:
    """Report `msg` as one line (`notices.warn`: the `mpcpearl_jax` logger)."""
    from mpcpearl_jax.notices import warn as notice

    notice(msg)


def read_log(path: Path, upto: int = 10**9, report: Callable[[str], None] = warn) -> list[dict]:
    """Rows of metrics.jsonl with iteration <= upto. A torn last line (a process killed while
    appending it) is dropped with a warning naming the file; a bad line elsewhere is an error."""
    if not path.is_file():
        return []
    lines = path.read_bytes().split(b"\n")
    rows = []
    for i, raw in enumerate(lines):
        if not raw.strip():
            continue
        try:
            rows.append(json.loads(raw))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            if any(x.strip() for x in lines[i + 1 :]):
                raise CheckpointError(
                    f"{path}: line {i + 1} is not JSON ({e}); repair or delete that line to "
                    "resume (that iteration's logged numbers are lost), or start again with "
                    "--overwrite"
                ) from e
            report(f"warning: {path}: dropped a torn last line (line {i + 1}, {len(raw)} bytes)")
    return [r for r in rows if r.get("iteration", 0) <= upto]


def write_log(path: Path, rows: list[dict]) -> None:
    atomic_write(path, "".join(json.dumps(r) + "\n" for r in rows))


def append_log(path: Path, row: dict) -> None:
    """Append one line with a single write on an O_APPEND descriptor: a crash leaves at most a
    torn last line (dropped on resume), never a mixed one."""
    data = (json.dumps(row) + "\n").encode()
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
        finally:
            os.close(fd)
    except OSError as e:  # e.g. a full disk: name the file
        raise OSError(e.errno, e.strerror or str(e), str(path)) from e
