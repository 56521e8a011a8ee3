"""Per-call latency of the MPC's SQP: the host solver on OSQP against the device solver (JAX),
for a batch of 1 and of 16 rows, on the gate's problems recorded from training
(`tests/data/mpc_problems.npz`, `benchmarks.record_mpc_problems`).

OSQP solves a call's rows one after the other on the host (the bridge with one worker); the
device solver solves them in one jitted, vmapped call (compilation excluded, reported apart).
The GP prediction, the same for both, is not included.

    python -m benchmarks.mpc_solvers [--tiny] [--batches 1 16] [--calls N] [--out DIR]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks import harness

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "mpc_problems.npz"


def _problems(path):
    from benchmarks.record_mpc_problems import regenerate, solver_params_of

    with np.load(path) as f:
        data = {k: f[k] for k in f.files}
    params = solver_params_of(data)
    return data, params, regenerate(data, params.num_samples)


def osqp_call(params, probs, data, rows):
    """Seconds of one call on `rows` with the host solver (sequential rows)."""
    import time

    from mpcpearl_jax.mpc.solver import RowProblem, SQPSolver

    solver = SQPSolver(params)
    t0 = time.perf_counter()
    for i in rows:
        row = RowProblem(*(a[i].astype(np.float64) if a.dtype.kind == "f" else a[i] for a in probs))
        init = data["u_init"][i].astype(np.float64) if data["has_init"][i] else None
        solver.solve(row, init)
    return time.perf_counter() - t0


def device_timing(params, probs, data, rows, calls, qp_iters):
    """harness.time_fn record of the jitted batched device solve on `rows`."""
    import jax
    import jax.numpy as jnp

    from mpcpearl_jax.mpc.device_solver import make_batch_solver

    solve = jax.jit(make_batch_solver(params, qp_iters))
    part = jax.tree_util.tree_map(lambda a: jnp.asarray(a[rows]), probs)
    u0, has = jnp.asarray(data["u_init"][rows]), jnp.asarray(data["has_init"][rows])
    return harness.time_fn(
        lambda: solve(part, u0, has), repeats=calls, warmup=1, block=jax.block_until_ready
    )


def main(argv: list[str] | None = None) -> None:
    ap = harness.common_parser(__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--calls", type=int, default=None, help="timed calls per batch size")
    ap.add_argument("--data", default=str(DATA))
    args = ap.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    calls = args.calls or (3 if args.tiny else 10)
    data, params, probs = _problems(args.data)
    from mpcpearl_jax.mpc.config import MPCConfig

    qp_iters = MPCConfig().device_qp_iters
    n = data["x0"].shape[0]
    rng = np.random.default_rng(0)
    rows_out = []
    for b in args.batches:
        sets = [rng.choice(n, b, replace=False) for _ in range(calls)]
        host = [osqp_call(params, probs, data, rows) for rows in sets]
        dev = device_timing(params, probs, data, sets[0], calls, qp_iters)
        for name, med, first in (
            ("osqp (host)", float(np.median(host)), None),
            ("device (jit, vmap)", dev["median_s"], dev["first_call_s"]),
        ):
            rows_out.append(
                {
                    "solver": name,
                    "batch": b,
                    "median_ms": 1e3 * med,
                    "per_row_ms": 1e3 * med / b,
                    "first_call_s": first,
                }
            )
        rows_out[-2]["raw_s"], rows_out[-1]["raw_s"] = host, dev["raw_s"]
    harness.print_table(
        rows_out,
        ["solver", "batch", "median_ms", "per_row_ms", "first_call_s"],
        title=f"MPC SQP per call ({n} recorded problems, {calls} calls each)",
    )
    harness.write_record(
        "mpc_solvers",
        {
            "size": harness.size_of(args),
            "batches": args.batches,
            "calls": calls,
            "device_qp_iters": qp_iters,
            **threads,
        },
        {"rows": rows_out},
        args.out,
    )


if __name__ == "__main__":
    main()
