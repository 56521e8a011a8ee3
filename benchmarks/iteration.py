"""One meta-training iteration, broken down: collection, GP, MPC solves, callback, updates.

Runs `Trainer.iteration` of a preset with MPC infusion at eps = 0.2. The buffers are first
filled by iteration 0 (initial collection over every training task) run without MPC (except at
`--tiny`, where MPC is cheap); then one
eps = 0.2 iteration compiles everything (its time is reported separately) and `--iterations`
more are timed. Per measured iteration:
  * updates: the jitted `lax.scan` of gradient steps (`update_s` of the trainer's log);
  * MPC solves: the host SQP time summed over solved rows (the bridge's per-row `solve_s`);
  * callback overhead: host time inside the callbacks that is not solving (marshalling rows,
    warm starts, fallbacks), i.e. sum(host_call_s) - sum(solve_s);
  * GP: the number of callbacks times the latency of the jitted GP prediction for the
    collection batch, measured separately (it runs inside the jitted collection);
  * collection (rest): the collection wall time minus the three above: env steps, policy,
    buffer inserts and the device/host transfers of the callbacks.
The default size shortens the update phase (`updates_per_iteration`, recorded) and also reports
the update phase scaled to the paper's 750 steps from the measured time per step.

    python -m benchmarks.iteration [--tiny | --full] [--out DIR] [--threads N]
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

from benchmarks import harness

PAPER_UPDATES = 750
SIZES: dict[str, dict[str, Any]] = {
    # tiny: short episodes and a cheap MPC, only so that the script runs in seconds
    "tiny": dict(
        preset="smoke",
        updates=None,
        iterations=1,
        initial_without_mpc=False,  # MPC is cheap here: one trainer, fewer compilations
        env={"horizon": 10},
        mpc={"horizon": 3, "num_samples": 20, "gp_mode": "fixed", "sqp_iters": 1},
    ),
    "default": dict(
        preset="paper", updates=50, iterations=2, initial_without_mpc=True, env={}, mpc={}
    ),
    "full": dict(
        preset="paper", updates=None, iterations=3, initial_without_mpc=True, env={}, mpc={}
    ),
}


def build(sz: dict[str, Any], eps: float = 0.2):
    from mpcpearl_jax.config import preset
    from mpcpearl_jax.training.trainer import Trainer

    cfg = preset(sz["preset"])
    changes: dict[str, Any] = {"eps": eps}
    if sz["updates"] is not None:
        changes["updates_per_iteration"] = sz["updates"]
    cfg = cfg.replace(
        seeds=1,
        train=dataclasses.replace(cfg.train, **changes),
        env_overrides={**cfg.env_overrides, **sz["env"]},
        mpc=cfg.mpc.replace(**sz["mpc"]),
    )
    return Trainer(cfg)


def gp_latency(trainer) -> float:
    """Seconds of one jitted GP prediction for the batch of a collection phase."""
    import jax

    tc = trainer.cfg.train
    rows = tc.tasks_per_iteration * max(tc.prior_episodes, tc.posterior_episodes)
    ids = jax.numpy.arange(rows) % trainer.num_train
    params = jax.tree_util.tree_map(lambda x: x[ids], trainer.train_tasks)
    _, states = jax.vmap(trainer.env.reset, in_axes=(None, 0))(jax.random.PRNGKey(0), params)
    states = states.replace(
        t=jax.numpy.minimum(states.t + 20, trainer.horizon - 1)
    )  # mid-episode: people have a history to fit
    predict = jax.jit(trainer.bridge.predict)
    key = jax.random.PRNGKey(1)
    t = harness.time_fn(
        lambda: predict(key, states, params),
        repeats=7,
        warmup=2,
        block=jax.block_until_ready,
        inner=5,
    )
    return t["median_s"]


def breakdown(log: dict[str, Any], stats: dict[str, Any], gp_s: float) -> dict[str, Any]:
    solve = float(sum(stats["solve_s"]))
    host = float(sum(stats["host_call_s"]))
    gp = stats["calls"] * gp_s
    return {
        "collection_rest_s": log["collect_s"] - host - gp,
        "gp_s_est": gp,
        "mpc_solves_s": solve,
        "callback_overhead_s": host - solve,
        "updates_s": log["update_s"],
        "total_s": log["collect_s"] + log["update_s"],
        "collect_s": log["collect_s"],
        "callbacks": stats["calls"],
        "rows_solved": stats["rows_solved"],
        "fallbacks": stats["fallbacks"],
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument("--iterations", type=int, default=None, help="measured iterations")
    args = p.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = dict(SIZES[size])
    if args.iterations:
        sz["iterations"] = args.iterations
    import jax

    # Iteration 0 (initial collection over every training task) without MPC, to fill the
    # buffers quickly; the state carries over to the eps = 0.2 trainer (same pytree).
    trainer = build(sz)
    state = trainer.init_state()
    initial_s = None
    if sz["initial_without_mpc"]:
        warm = build(sz, eps=0.0)
        t0 = time.perf_counter()
        state, _ = warm.iteration(state)
        jax.block_until_ready(state)
        initial_s = time.perf_counter() - t0
        del warm
    t0 = time.perf_counter()
    state, _ = trainer.iteration(state)  # compiles the eps = 0.2 phases
    jax.block_until_ready(state)
    first_s = time.perf_counter() - t0
    gp_s = gp_latency(trainer)

    rows = []
    for i in range(sz["iterations"]):
        trainer.bridge.reset_stats()
        state, log = trainer.iteration(state)
        rows.append({"iteration": i + 1, **breakdown(log, trainer.bridge.stats(), gp_s)})
    trainer.close()
    tc = trainer.cfg.train
    parts = ["collection_rest_s", "gp_s_est", "mpc_solves_s", "callback_overhead_s", "updates_s"]
    med = {k: harness.summarize([r[k] for r in rows])["median_s"] for k in parts + ["total_s"]}
    per_update = med["updates_s"] / tc.updates_per_iteration
    med_row = {"iteration": "median", **med}
    harness.print_table(
        rows + [med_row],
        ["iteration", *parts, "total_s", "callbacks", "rows_solved"],
        f"Meta-training iteration ({sz['preset']}, eps 0.2, "
        f"{tc.updates_per_iteration} updates, {trainer.steps_per_iteration()} "
        "env steps)",
    )
    summary = {
        "initial_collection_and_iteration_eps0_s_incl_compile": initial_s,
        "first_eps02_iteration_s_incl_compile": first_s,
        "gp_call_s": gp_s,
        "s_per_update": per_update,
        "updates_scaled_to_750_s": per_update * PAPER_UPDATES,
        "iteration_scaled_to_750_updates_s": med["total_s"]
        - med["updates_s"]
        + per_update * PAPER_UPDATES,
        "shares": {k: med[k] / med["total_s"] for k in parts},
    }
    print(
        f"first eps 0.2 iteration (incl. compile) {first_s:.1f} s; "
        f"{per_update * 1e3:.1f} ms per update; iteration scaled to 750 updates "
        f"{summary['iteration_scaled_to_750_updates_s']:.1f} s",
        flush=True,
    )
    results = {"iterations": rows, "median": med, "summary": summary}
    config = {
        "size": size,
        **sz,
        "threads": threads,
        "experiment": trainer.cfg.to_dict(),
        "env_steps_per_iteration": trainer.steps_per_iteration(),
    }
    harness.write_record("iteration", config, results, args.out)
    return results


if __name__ == "__main__":
    main()
