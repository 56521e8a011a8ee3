"""Record MPC problems from fired rows of real training: the data of the SQP's convergence curve
(`lab.convergence`), its tests (`tests/test_mpc_sqp_convergence.py`) and `benchmarks.mpc_solvers`.

Runs the `cpu-explore` preset on the restaurant tasks (one seed, eps 0.2 unless set) for at most
`--seconds`, and records every SQP problem the bridge hands to its host solver (`RowProblem`)
with the warm-start plan it got (the shifted previous plan, or a cold start), in the format that
`mpcpearl_jax.mpc.recorded` reads: per problem, the pose, goal, static obstacles, the GP
prediction's per-stage mean and variance of each person (estimated from the row's M samples) and
the warm-start plan, all float32; the samples are regenerated from them with a stored per-problem
key (`recorded.regenerate`). The host solver on OSQP then solves every regenerated problem, and
its first input, reason and decision are stored too.

    python -m benchmarks.record_mpc_problems [--seconds 90] [--count 1200]
        [--out tests/data/mpc_problems.npz]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

from mpcpearl_jax.mpc.recorded import (
    Recorded,
    params_record,
    qp_settings_of,
    regenerate,
    solver_params_of,
)

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "tests" / "data" / "mpc_problems.npz"


def record(seconds: float, count: int, eps: float) -> tuple[list, list, dict]:
    """(problems, warm-start plans or None, solver params as a dict) from a training run."""
    from mpcpearl_jax.config import resolve
    from mpcpearl_jax.mpc.host import HostSolver
    from mpcpearl_jax.mpc.problem import solver_params
    from mpcpearl_jax.mpc.qp_osqp import OSQPSettings
    from mpcpearl_jax.training.trainer import Trainer

    cfg = resolve("cpu-explore", env="restaurant")
    cfg = cfg.replace(
        train=dataclasses.replace(cfg.train, eps=eps, eval_interval=0),
        mpc=cfg.mpc.replace(n_workers=1),
    )
    probs, inits, sizes = [], [], []
    original = HostSolver.solve_rows

    def recording(self, rows, warm, num_static):
        probs.extend(rows)
        inits.extend(warm)
        sizes.append(num_static)
        return original(self, rows, warm, num_static)

    HostSolver.solve_rows = recording  # type: ignore[method-assign]
    try:
        tr = Trainer(cfg)
        state = tr.init_state()
        t0 = time.perf_counter()
        while len(probs) < count and time.perf_counter() - t0 < seconds:
            state, _ = tr.iteration(state)
            print(f"{time.perf_counter() - t0:6.1f} s: {len(probs)} problems", flush=True)
        params = solver_params(cfg.mpc, tr.env.config, sizes[0])
        tr.close()
    finally:
        HostSolver.solve_rows = original  # type: ignore[method-assign]
    return probs, inits, params_record(params, OSQPSettings.from_config(cfg.mpc))


def compress(probs: list, inits: list, params: dict) -> dict[str, np.ndarray]:
    """The arrays of the file (float32; GP samples as mean and variance plus a key seed)."""
    k = params["horizon"]
    samples = np.stack([p.samples for p in probs])  # [N, K, NA, M, 2]
    out = {
        "x0": np.stack([p.x0 for p in probs]),
        "goal": np.stack([p.goal for p in probs]),
        "mean": samples.mean(axis=3),
        "var": samples.var(axis=3),
        "valid": np.stack([p.valid for p in probs]),
        "static_lo": np.stack([p.static_lo for p in probs]),
        "static_hi": np.stack([p.static_hi for p in probs]),
        "static_radius": np.stack([p.static_radius for p in probs]),
        "u_init": np.stack([np.zeros((k, 2)) if u is None else u for u in inits]),
        "has_init": np.array([u is not None for u in inits]),
    }
    out = {n: a.astype(np.float32) if a.dtype.kind == "f" else a for n, a in out.items()}
    out["seed"] = np.arange(len(probs), dtype=np.uint32)
    out["params"] = np.array(json.dumps(params))
    return out


def solve_reference(data) -> dict[str, np.ndarray]:
    """The host solver on OSQP on every regenerated problem: first input, reason, ok."""
    from mpcpearl_jax.mpc.sqp import SQPSolver

    params = solver_params_of(data)
    solver = SQPSolver(params, qp_settings_of(data))
    batch = regenerate(data, params.num_samples)
    rec = Recorded(data, params, solver.qp, batch)
    first, reason, ok = [], [], []
    for i in range(len(rec)):
        res = solver.solve(*rec.row(i))
        first.append(res.u[0])
        reason.append(res.reason)
        ok.append(res.ok)
    return {
        "osqp_first": np.asarray(first, np.float32),
        "osqp_reason": np.asarray(reason),
        "osqp_ok": np.asarray(ok),
    }


def check_out(out: str | Path) -> Path:
    """--out must name a file in a folder that can be written (created if missing): one line
    and exit 2 otherwise (`harness.fail`), before the training runs; a path ending in "/" names
    a folder, there or not. -> the file's path."""
    from benchmarks.harness import fail
    from mpcpearl_jax.validate import unwritable_folder

    if str(out).endswith(("/", os.sep)) or Path(out).is_dir():
        fail(f"--out {out}: a folder; give the file's name (NAME.npz)")
    out = Path(out)
    why = unwritable_folder(out.parent)
    if why is not None:
        fail(f"--out {out}: not writable ({why}); choose another --out")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=90.0, help="training budget (s)")
    ap.add_argument("--count", type=int, default=1200, help="problems to keep")
    ap.add_argument("--eps", type=float, default=0.2)
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="the problems' file (NAME.npz)")
    args = ap.parse_args(argv)
    args.out = check_out(args.out)  # before the training, not after it
    probs, inits, params = record(args.seconds, args.count, args.eps)
    if len(probs) > args.count:  # evenly over the run
        keep = np.linspace(0, len(probs) - 1, args.count).round().astype(int)
        probs, inits = [probs[i] for i in keep], [inits[i] for i in keep]
    data = compress(probs, inits, params)
    data.update(solve_reference(data))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **data)
    reasons = dict(zip(*np.unique(data["osqp_reason"], return_counts=True), strict=True))
    print(
        f"{len(probs)} problems -> {args.out} ({args.out.stat().st_size / 1e6:.2f} MB); {reasons}"
    )


if __name__ == "__main__":
    main()
