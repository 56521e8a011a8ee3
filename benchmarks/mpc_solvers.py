"""Per-call latency of the MPC's SQP on OSQP (the host solver, `mpc.host`), for a batch of 1 and
of 16 rows, on problems recorded from training (`tests/data/mpc_problems.npz`,
`benchmarks.record_mpc_problems`).

A call's rows are solved one after the other, as the bridge does with one worker. The GP
prediction is not included. (The device solver this once compared against was removed: its
records stay in `benchmarks/results/`, docs/method.md §6 says why.)

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

    from mpcpearl_jax.mpc.host import SQPSolver
    from mpcpearl_jax.mpc.problem import RowProblem

    solver = SQPSolver(params)
    t0 = time.perf_counter()
    for i in rows:
        row = RowProblem(*(a[i].astype(np.float64) if a.dtype.kind == "f" else a[i] for a in probs))
        init = data["u_init"][i].astype(np.float64) if data["has_init"][i] else None
        solver.solve(row, init)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> None:
    ap = harness.common_parser(__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--calls", type=int, default=None, help="timed calls per batch size")
    ap.add_argument("--data", default=str(DATA))
    args = ap.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    calls = args.calls or (3 if args.tiny else 10)
    data, params, probs = _problems(args.data)
    n = data["x0"].shape[0]
    rng = np.random.default_rng(0)
    rows_out = []
    for b in args.batches:
        sets = [rng.choice(n, b, replace=False) for _ in range(calls)]
        host = [osqp_call(params, probs, data, rows) for rows in sets]
        med = float(np.median(host))
        rows_out.append(
            {
                "solver": "osqp (host)",
                "batch": b,
                "median_ms": 1e3 * med,
                "per_row_ms": 1e3 * med / b,
                "raw_s": host,
            }
        )
    harness.print_table(
        rows_out,
        ["solver", "batch", "median_ms", "per_row_ms"],
        title=f"MPC SQP per call ({n} recorded problems, {calls} calls each)",
    )
    harness.write_record(
        "mpc_solvers",
        {
            "size": harness.size_of(args),
            "batches": args.batches,
            "calls": calls,
            **threads,
        },
        {"rows": rows_out},
        args.out,
    )


if __name__ == "__main__":
    main()
