"""MPC latency per call in a closed loop on restaurant test tasks (method §6 target on a 2-core CPU:
median <= 10 ms and p95 <= 40 ms per MPC call at K = 10, M = 100, 2 people, 5 tables).

Each task runs one GP-MPC episode (MPC at every step) as a jitted `lax.scan` with batch 1, so
every host callback solves one row. Reported per call:
  - solve: the host SQP (linearization, OSQP QPs, line search, safety check);
  - host callback: solve plus unpacking the batch and merging actions;
  - MPC call: the host callback plus the mean per-step overhead outside it (GP prediction in
    JAX, callback transfer, env step), measured as episode wall time minus callback time;
  - GP: the jitted GP prediction (fit + K-step propagation + M samples) for the batch alone;
and the QP iterations, QPs per call and the status counts.

    python -m benchmarks.mpc_latency [--tasks N] [--out DIR | --record] [--gp-mode fit|fixed]
"""

from __future__ import annotations

import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import harness
from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.envs.types import EnvState
from mpcpearl_jax.mpc import MPCConfig, make_gp_mpc_rollout, make_mpc_bridge


def _pct(xs, q):
    return float(np.percentile(np.asarray(xs) * 1e3, q))


def closed_loop(env, tasks, cfg, num_tasks):
    """Run one episode per task with batch 1; returns (bridge stats, wall seconds per step)."""
    bridge = make_mpc_bridge(env, cfg)
    rollout = jax.jit(make_gp_mpc_rollout(env, bridge))
    one = lambda i: jax.tree_util.tree_map(lambda a: a[i : i + 1], tasks)  # noqa: E731
    jax.block_until_ready(rollout(jax.random.PRNGKey(0), one(0)))  # compile
    bridge.reset_stats()
    wall = []
    for i in range(num_tasks):
        t0 = time.perf_counter()
        jax.block_until_ready(rollout(jax.random.PRNGKey(i), one(i)))
        wall.append((time.perf_counter() - t0) / env.config.horizon)
    return bridge.stats(), wall


def gp_cost(env, tasks, cfg, batch):
    """Seconds for the jitted GP prediction of `batch` rows (timed with the harness)."""
    bridge = make_mpc_bridge(env, cfg)
    params = jax.tree_util.tree_map(lambda a: a[np.arange(batch) % a.shape[0]], tasks)
    states = EnvState(pose=params.start, t=jnp.full(batch, 30, jnp.int32))
    fn = jax.jit(bridge.predict)
    return harness.time_fn(
        lambda: fn(jax.random.PRNGKey(0), states, params),
        repeats=20,
        warmup=2,
        block=jax.block_until_ready,
    )


def main(argv: list[str] | None = None) -> None:
    ap = harness.BenchmarkParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=int, default=24, help="episodes, one per test task (1-24)")
    harness.add_out_options(ap)
    ap.add_argument("--gp-mode", default="fit", choices=("fit", "fixed"))
    args = ap.parse_args(argv)
    harness.check_platform_or_fail()
    tasks = make_tasks("restaurant", "test")
    if not 1 <= args.tasks <= tasks.num_tasks:  # before the episodes, not after them
        harness.fail(
            f"--tasks {args.tasks}: give 1 to {tasks.num_tasks} (the restaurant's test split "
            "has that many tasks)"
        )
    env = make_env("restaurant")
    cfg = MPCConfig(gp_mode=args.gp_mode)
    num_tasks = args.tasks
    stats, wall = closed_loop(env, tasks, cfg, num_tasks)
    gp1, gp24 = gp_cost(env, tasks, cfg, 1), gp_cost(env, tasks, cfg, 24)
    # GP + callback transfer + env step, per step: episode wall time minus the host callbacks
    overhead_s = float(np.mean(wall) - np.mean(stats["host_call_s"]))
    per_call = np.asarray(stats["host_call_s"]) + overhead_s
    rows = []
    for name, xs in (
        ("solve", stats["solve_s"]),
        ("host callback", stats["host_call_s"]),
        ("MPC call (callback + GP + transfer)", per_call),
        ("episode mean per step", wall),
    ):
        rows.append(
            {
                "what": name,
                "median_ms": _pct(xs, 50),
                "p95_ms": _pct(xs, 95),
                "mean_ms": float(np.mean(xs) * 1e3),
                "max_ms": _pct(xs, 100),
                "n": len(xs),
            }
        )
    for name, r in (("GP (batch 1)", gp1), ("GP (batch 24)", gp24)):
        rows.append(
            {
                "what": name,
                "median_ms": r["median_s"] * 1e3,
                "mean_ms": statistics.mean(r["raw_s"]) * 1e3,
                "max_ms": r["max_s"] * 1e3,
                "n": len(r["raw_s"]),
            }
        )
    harness.print_table(
        rows,
        ["what", "median_ms", "p95_ms", "mean_ms", "max_ms", "n"],
        title=f"MPC latency, restaurant test, {num_tasks} episodes, batch 1",
    )
    summary = {
        "qp_iters_median": float(np.median(stats["qp_iters"])),
        "qp_iters_p95": float(np.percentile(stats["qp_iters"], 95)),
        "qps_per_call_mean": float(np.mean(stats["n_qp"])),
        "status_counts": stats["status"],
        "reasons": stats["reasons"],
        "gp_transfer_env_overhead_ms_per_step": overhead_s * 1e3,
        "target_met": _pct(per_call, 50) <= 10.0 and _pct(per_call, 95) <= 40.0,
    }
    for k, v in summary.items():
        print(f"{k}: {v}")
    harness.write_record(
        "mpc_latency",
        {
            "mpc": cfg.to_dict(),
            "tasks": num_tasks,
            "env": "restaurant",
            "split": "test",
            "jax_threads_note": "CPU backend",
        },
        {
            "rows": rows,
            "summary": summary,
            "raw_solve_s": stats["solve_s"],
            "raw_step_s": wall,
            "gp_batch1": gp1,
            "gp_batch24": gp24,
        },
        args.out,
    )


if __name__ == "__main__":
    main(sys.argv[1:])
