"""Fingerprint of what training computes: a redesign must not change the algorithm.

Two iterations of the `paper`, `cpu-explore` and `default` presets, shrunk to test sizes (small
networks, two tasks per iteration, three gradient steps; every algorithmic option of the preset
kept, the MPC infusion included), on the restaurant tasks; the training metrics of each iteration
and a checksum of the trained parameters are compared with `tests/data/fingerprint.json`,
recorded before any restructuring of the training code. Floating-point results can differ in the
last bits between CPUs (vectorisation, fused multiply-add), so values are compared to 1e-4
relative; a changed algorithm (another key split, loss term, update order) moves them by far
more than that.

The MPC's host solve is replaced here by a deterministic stand-in (`stand_in_solve_rows`):
the fingerprint covers when the MPC is called, which rows it acts on, how its actions, fallbacks
and statistics enter the buffers and the updates, not the SQP's own numbers (tests/test_mpc*.py
check those against references). The real solve's safe / unsafe decisions sit on thresholds of
GP samples fitted in float32, and they flip between CPUs: the fingerprint recorded with the real
solve on an AMD EPYC differed on an Intel Xeon by 5 of 191 fallbacks in the first iteration and
18 % in the second iteration's Q loss, with the same code and library versions.

Regenerate only when a change of the computed values is intended and stated:
    MPCPEARL_WRITE_FINGERPRINT=1 pytest tests/test_fingerprint.py -m ""
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import jax
import numpy as np
import pytest

from mpcpearl_jax.config import preset
from mpcpearl_jax.mpc.host import HostSolver
from mpcpearl_jax.mpc.problem import SolveResult

FILE = Path(__file__).parent / "data" / "fingerprint.json"
PRESETS = ("paper", "cpu-explore", "default")
ITERATIONS = 2


def tiny(name: str):
    """The preset with test sizes; its algorithm (every option, eps 0.2) unchanged."""
    cfg = preset(name)
    pearl = cfg.pearl.replace(
        hidden=(16, 16),
        encoder_hidden=(16,),
        latent_dim=3,
        meta_batch=2,
        batch_size=16,
        context_size=8,
    )
    train = dataclasses.replace(
        cfg.train,
        eps=0.2,
        iterations=ITERATIONS,
        initial_episodes=1,
        tasks_per_iteration=2,
        prior_episodes=1,
        posterior_episodes=1,
        updates_per_iteration=3,
        rl_capacity=400,
        eval_interval=0,
        checkpoint_interval=1,
    )
    mpc = cfg.mpc.replace(num_samples=20, qp_tail_samples=5, n_workers=1)
    return cfg.replace(pearl=pearl, train=train, mpc=mpc, seeds=1)


def stand_in_solve_rows(self, probs, inits, num_static):
    """In place of `HostSolver.solve_rows`: for each fired row a constant plan towards the goal
    (speed min(2, distance), steering the heading error clipped to 0.35 rad, both rounded to
    0.01), safe except on every third warm-started call, which falls back to the shifted plan
    (exercising the bridge's fallback path); deterministic in the rows' poses and goals."""
    count = getattr(self, "_stand_in_calls", 0)
    out = []
    for p, u0 in zip(probs, inits, strict=True):
        d = p.goal - p.x0[:2]
        err = np.arctan2(d[1], d[0]) - p.x0[2]
        err = (err + np.pi) % (2 * np.pi) - np.pi
        u = np.array([min(2.0, float(np.hypot(*d))), float(np.clip(err, -0.35, 0.35))])
        u = np.round(u, 2)
        count += 1
        ok = u0 is None or count % 3 != 0
        plan = np.tile(u, (self.cfg.horizon, 1))
        poses = np.tile(p.x0, (self.cfg.horizon + 1, 1))
        out.append(SolveResult(plan, poses, ok, "solved" if ok else "unsafe", 1, 1, 0.0, 0.0))
    self._stand_in_calls = count
    return out


def fingerprint(name: str) -> dict:
    from mpcpearl_jax.training.trainer import Trainer

    tr = Trainer(tiny(name))
    state = tr.init_state()
    logs = []
    for _ in range(ITERATIONS):
        state, log = tr.iteration(state)
        logs.append(
            {
                k: float(np.mean(v))
                for k, v in sorted(log.items())
                # every computed number the iteration logs (wall times, "*_s", are not)
                if not k.endswith("_s") and np.asarray(v).dtype.kind in "fiub"
            }
        )
    leaves = jax.tree_util.tree_leaves(state.learner.params)
    checksum = {
        "abs_sum": float(sum(np.abs(np.asarray(x, np.float64)).sum() for x in leaves)),
        "sum": float(sum(np.asarray(x, np.float64).sum() for x in leaves)),
    }
    return {"iterations": logs, "params": checksum}


@pytest.mark.parametrize(
    "name",
    # the paper's algorithm in every run of the suite; the extended presets (about a minute
    # each) with the slow tests: run them with `pytest -m slow tests/test_fingerprint.py`
    [PRESETS[0], *(pytest.param(n, marks=pytest.mark.slow) for n in PRESETS[1:])],
)
def test_training_computes_what_it_computed(name, monkeypatch):
    monkeypatch.setattr(HostSolver, "solve_rows", stand_in_solve_rows)
    got = fingerprint(name)
    if os.environ.get("MPCPEARL_WRITE_FINGERPRINT") == "1":
        data = json.loads(FILE.read_text()) if FILE.exists() else {}
        data[name] = got
        FILE.parent.mkdir(parents=True, exist_ok=True)
        FILE.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
        pytest.skip(f"fingerprint of {name!r} written to {FILE.name}")
    want = json.loads(FILE.read_text())[name]
    assert len(got["iterations"]) == len(want["iterations"])
    for i, (g, w) in enumerate(zip(got["iterations"], want["iterations"], strict=True)):
        assert sorted(g) == sorted(w), f"iteration {i + 1}: logged metrics changed"
        for k in w:
            assert g[k] == pytest.approx(w[k], rel=1e-4, abs=1e-5), f"iteration {i + 1}: {k}"
    for k, v in want["params"].items():
        assert got["params"][k] == pytest.approx(v, rel=1e-4, abs=1e-5), f"parameters: {k}"
