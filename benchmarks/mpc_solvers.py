"""Per-call latency of the MPC's SQP (`mpc.sqp`) through its QP backend (`mpc.qp.QPBackend`), for
a batch of 1 and of 16 rows, on problems recorded from training (`tests/data/mpc_problems.npz`,
`mpcpearl_jax.mpc.recorded`).

Each backend of `BACKENDS` (OSQP, `mpc.qp_osqp`, with the recorded settings) is timed through
the protocol: the SQP solves a call's rows one after the other, as the bridge does with one
worker, and a wrapper around the backend (`TimedQP`) measures the time spent in its `setup`,
`update` and `solve`, the rest being the SQP's own NumPy work (linearization, line search,
safety check). The GP prediction is not included. (The device solver this once compared against
was removed: its records stay in `benchmarks/results/`, docs/method.md §6 says why.)

    python -m benchmarks.mpc_solvers [--tiny] [--batches 1 16] [--calls N] [--out DIR]
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import harness

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "mpc_problems.npz"
# name -> the backend's settings for a recorded file (`recorded.Recorded`)
BACKENDS = {"osqp": lambda rec: rec.qp}
_QP_SECONDS: list[float] = []  # time inside the timed backends, since the last clear


class _TimedBackend:
    """A `QPBackend` that times the calls it passes on to another."""

    def __init__(self, inner: Any):
        self.inner = inner

    def _timed(self, name: str, *args: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return getattr(self.inner, name)(*args)
        finally:
            _QP_SECONDS.append(time.perf_counter() - t0)

    def setup(self, *args: Any) -> None:
        self._timed("setup", *args)

    def update(self, *args: Any) -> None:
        self._timed("update", *args)

    def solve(self, *args: Any) -> Any:
        return self._timed("solve", *args)


@dataclasses.dataclass(frozen=True)
class TimedQP:
    """QP settings (`mpc.qp.QPSettings`) whose backend is `inner`'s, timed."""

    inner: Any

    def backend(self) -> _TimedBackend:
        return _TimedBackend(self.inner.backend())


def timed_call(rec, qp, rows) -> tuple[float, float]:
    """(seconds of one call on `rows`, seconds of it inside the QP backend), rows one after the
    other on a new solver (its backend set up by the call's first QP)."""
    from mpcpearl_jax.mpc.sqp import SQPSolver

    solver = SQPSolver(rec.params, TimedQP(qp))
    _QP_SECONDS.clear()
    t0 = time.perf_counter()
    for i in rows:
        solver.solve(*rec.row(i))
    return time.perf_counter() - t0, float(sum(_QP_SECONDS))


def main(argv: list[str] | None = None) -> None:
    from mpcpearl_jax.mpc import recorded

    ap = harness.common_parser(__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--calls", type=int, default=None, help="timed calls per batch size")
    ap.add_argument("--data", default=str(DATA))
    args = ap.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    calls = args.calls or (3 if args.tiny else 10)
    rec = recorded.load(args.data)
    n = len(rec)
    rows_out = []
    for name, settings_of in BACKENDS.items():
        rng = np.random.default_rng(0)  # the same rows for every backend
        for b in args.batches:
            sets = [rng.choice(n, b, replace=False) for _ in range(calls)]
            timed = [timed_call(rec, settings_of(rec), rows) for rows in sets]
            wall = [t for t, _ in timed]
            med = float(np.median(wall))
            rows_out.append(
                {
                    "solver": f"sqp, {name}",
                    "batch": b,
                    "median_ms": 1e3 * med,
                    "per_row_ms": 1e3 * med / b,
                    "qp_share": float(np.median([q / t for t, q in timed])),
                    "raw_s": wall,
                    "qp_s": [q for _, q in timed],
                }
            )
    harness.print_table(
        rows_out,
        ["solver", "batch", "median_ms", "per_row_ms", "qp_share"],
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
