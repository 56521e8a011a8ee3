"""The device solver's gate on every recorded MPC problem (tests/data/mpc_problems.npz): the share
of problems whose first input is within 0.02 normalized units of OSQP's, and whose decision
(solved / least violation / fallback) is OSQP's; with the compile and solve times.

    python -m benchmarks.mpc_gate [--qp-iters 30] [--chunk 1200] [--out gate.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.record_mpc_problems import regenerate, solver_params_of
from mpcpearl_jax.envs.dynamics import to_normalized
from mpcpearl_jax.mpc import device_solver as ds

FILE = Path(__file__).resolve().parents[1] / "tests" / "data" / "mpc_problems.npz"
V_MAX_ENV = 5.0  # restaurant's v_max: the normalization of the actions


def _decision(reason) -> np.ndarray:
    reason = np.asarray(reason)
    return np.where(reason == "solved", 0, np.where(reason == "least_violation", 1, 2))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--qp-iters", type=int, default=30)
    ap.add_argument("--chunk", type=int, default=1200)
    ap.add_argument("--rows", type=int, default=0, help="0: every recorded problem")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    with np.load(FILE) as f:
        data = {k: f[k] for k in f.files}
    n_all = data["x0"].shape[0]
    n = args.rows or n_all
    rows = np.linspace(0, n_all - 1, n).round().astype(int)
    p = solver_params_of(data)
    probs = regenerate({k: v[rows] for k, v in data.items() if k != "params"}, p.num_samples)
    solve = jax.jit(ds.make_batch_solver(p, args.qp_iters))
    first, reason, times = [], [], []
    for i in range(0, n, args.chunk):
        sl = slice(i, i + args.chunk)
        part = jax.tree_util.tree_map(lambda a, sl=sl: jnp.asarray(a[sl]), probs)
        t0 = time.perf_counter()
        res = jax.block_until_ready(
            solve(
                part, jnp.asarray(data["u_init"][rows][sl]), jnp.asarray(data["has_init"][rows][sl])
            )
        )
        times.append(time.perf_counter() - t0)
        first.append(np.asarray(res.u[:, 0]))
        reason.extend(ds.REASONS[int(r)] for r in np.asarray(res.reason))
    # a second pass over the first chunk: the solve without compilation
    sl = slice(0, args.chunk)
    part = jax.tree_util.tree_map(lambda a: jnp.asarray(a[sl]), probs)
    t0 = time.perf_counter()
    jax.block_until_ready(
        solve(part, jnp.asarray(data["u_init"][rows][sl]), jnp.asarray(data["has_init"][rows][sl]))
    )
    warm = time.perf_counter() - t0
    first, reason = np.concatenate(first), np.asarray(reason)
    ref = data["osqp_first"][rows]
    gap = np.max(
        np.abs(np.asarray(to_normalized(first, V_MAX_ENV) - to_normalized(ref, V_MAX_ENV))), 1
    )
    same = _decision(reason) == _decision(data["osqp_reason"][rows])
    rec = {
        "problems": int(n),
        "qp_iters": args.qp_iters,
        "chunk": args.chunk,
        "within_0.02": float(np.mean(gap <= 0.02)),
        "same_decision": float(np.mean(same)),
        "gap_quantiles_50_90_99": [float(x) for x in np.quantile(gap, [0.5, 0.9, 0.99])],
        "device_reasons": {r: int(np.sum(reason == r)) for r in np.unique(reason)},
        "osqp_reasons": {
            r: int(np.sum(data["osqp_reason"][rows] == r))
            for r in np.unique(data["osqp_reason"][rows])
        },
        "first_call_s": times[0],
        "solve_s_per_chunk_after_compile": warm,
        "device": str(jax.devices()[0]),
    }
    print(json.dumps(rec, indent=1))
    if args.out:
        args.out.write_text(json.dumps(rec, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
