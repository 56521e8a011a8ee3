"""Fault injection on saved policies and records: wrong `load_policy` inputs, non-finite
parameters refused on save and load, results.json without NaN or Infinity, and a GrBAL folder
given to `load_policy`."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.deploy.policy import load_policy
from mpcpearl_jax.training.checkpoint import CheckpointError


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


def _nan_policy(run: Path) -> Path:
    from flax import serialization

    pfile = run / "policy.msgpack"
    raw = serialization.msgpack_restore(pfile.read_bytes())
    nan = jax.tree_util.tree_map(lambda x: np.full_like(x, np.nan), raw)
    pfile.write_bytes(serialization.msgpack_serialize(nan))
    return pfile


def test_non_finite_parameters_are_refused_on_save_and_load(tmp_path, ref0, capsys):
    from mpcpearl_jax.cli import evaluate
    from mpcpearl_jax.runfolder import save_params
    from mpcpearl_jax.training.checkpoint import Checkpointer

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
    from mpcpearl_jax.cli import evaluate
    from mpcpearl_jax.runfolder import strict_json

    doc = _strict(strict_json({"a": float("nan"), "b": [1.0, float("-inf")], "c": 2}))
    assert doc["a"] is None and doc["b"] == [1.0, None] and doc["c"] == 2
    assert set(doc["null_values"]) == {"a", "b[1]"} and "NaN" in doc["null_values"]["a"]
    out = tmp_path / "seeds"
    argv = [str(ref0), "--task-seeds", "0-0", "--tasks", "0", "--out", str(out)]
    assert evaluate.main(argv) == 0
    rec = _strict((out / "results.json").read_text())
    assert rec["pooled"]["SR"]["se"] is None and "pooled.SR.se" in rec["null_values"]


def test_load_policy_on_a_grbal_run_says_what_it_is(tmp_path, capsys):
    from mpcpearl_jax.cli import evaluate
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
