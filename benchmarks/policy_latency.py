"""Policy inference latency through `load_policy` (batch 1 and 1024) vs. one MPC call.

The policy comes from a run directory (`--run DIR`); without one, an untrained agent of the
`paper` preset (method §7 sizes) is saved to a temporary run directory first: latency does not
depend on the weights. Timed: the jitted deterministic `act(obs, z)` at batch 1 and 1024, the
jitted `infer_z` on a 64-row context, and one MPC call: the jitted bridge (GP prediction in JAX +
the host SQP through the callback) for one fired env, stepped in a closed loop over restaurant
test tasks so that solves are warm-started as during training. Targets: policy >= 100x faster
than an MPC call, batch-1 policy under 100 microseconds.

    python -m benchmarks.policy_latency [--tiny | --full] [--out DIR | --record] [--threads N]
        [--run DIR]
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks import harness

SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(preset="smoke", mpc_tasks=1, mpc_steps=6, repeats=3, sample_s=0.02),
    "default": dict(preset="paper", mpc_tasks=4, mpc_steps=40, repeats=7, sample_s=0.2),
    "full": dict(preset="paper", mpc_tasks=24, mpc_steps=80, repeats=15, sample_s=0.5),
}


def save_untrained_run(run_dir: Path, preset_name: str) -> None:
    """A run directory (config + policy file) holding a freshly initialised agent."""
    import jax

    from mpcpearl_jax import make_env
    from mpcpearl_jax.config import preset
    from mpcpearl_jax.pearl.networks import Networks
    from mpcpearl_jax.runfolder import save_config
    from mpcpearl_jax.training.checkpoint import Checkpointer

    cfg = preset(preset_name)
    env = make_env(cfg.env)
    obs_dim = env.obs_dim(jax.tree_util.tree_map(lambda x: x[0], _test_tasks(cfg.env)))
    params = Networks(cfg.pearl, obs_dim, env.action_dim).init(jax.random.PRNGKey(0))
    stacked = jax.tree_util.tree_map(
        lambda x: x[None].repeat(cfg.seeds, 0), {k: params[k] for k in ("policy", "encoder")}
    )
    save_config(run_dir, cfg)
    ckpt = Checkpointer(run_dir, keep=1)
    ckpt.save(0, stacked, jax.device_get(stacked))
    ckpt.close()


def _test_tasks(env_name: str):
    from mpcpearl_jax import make_tasks

    return make_tasks(env_name, "test")


def policy_timings(policy, cfg: dict[str, Any]) -> list[dict[str, Any]]:
    """Median latency of jitted act at batch 1 / 1024 and of infer_z on 64 context rows."""
    import jax
    import jax.numpy as jnp

    act, infer = policy.jit()
    o, z = policy.obs_dim, policy.latent_dim
    inputs = {b: (jnp.zeros((b, o)), jnp.zeros((b, z))) for b in (1, 1024)}
    context = jnp.zeros((64, 2 * o + 2 + 1))
    cases = [
        ("act", 1, lambda: act(*inputs[1])),
        ("act", 1024, lambda: act(*inputs[1024])),
        ("infer_z (64 rows)", 1, lambda: infer(context)),
    ]
    rows = []
    for name, batch, fn in cases:
        _, first = harness.timed(lambda fn=fn: jax.block_until_ready(fn()))
        _, once = harness.timed(lambda fn=fn: jax.block_until_ready(fn()))
        t = harness.time_fn(
            fn,
            repeats=cfg["repeats"],
            block=jax.block_until_ready,
            inner=harness.calls_for(once, cfg["sample_s"]),
        )
        rows.append(
            {
                "call": name,
                "batch": batch,
                "latency_us": t["median_s"] * 1e6,
                "per_row_us": t["median_s"] * 1e6 / batch,
                "first_call_s": first,
                "timing": t,
            }
        )
    return rows


def mpc_timings(policy, cfg: dict[str, Any]) -> dict[str, Any]:
    """Latency of one MPC call (batch 1, always fired) along closed-loop episodes."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from mpcpearl_jax import make_env
    from mpcpearl_jax.mpc import make_mpc_bridge

    env = make_env(policy.config.env)
    tasks = _test_tasks(policy.config.env)
    bridge = make_mpc_bridge(env, policy.config.mpc)
    call = jax.jit(bridge.step)
    carry = bridge.init(1)  # no episode stamp: the plans are forgotten by reset_memory below
    act = jax.jit(policy.act)
    step = jax.jit(env.step)
    z = jnp.zeros((1, policy.latent_dim))
    fire = jnp.ones((1,), bool)
    key = jax.random.PRNGKey(0)
    lat, compile_s = [], None
    for i in range(cfg["mpc_tasks"]):
        params = jax.tree_util.tree_map(lambda x, i=i: x[i], tasks)
        batched = jax.tree_util.tree_map(lambda x: x[None], params)
        obs, state = env.reset(key, params)
        bridge.reset_memory()
        for t in range(cfg["mpc_steps"]):
            k = jax.random.fold_in(key, i * 1000 + t)
            states = jax.tree_util.tree_map(lambda x: x[None], state)
            a_pi = act(obs[None], z)
            jax.block_until_ready(a_pi)
            t0 = time.perf_counter()
            carry, actions, _, _ = call(carry, k, fire, states, batched, a_pi)
            jax.block_until_ready(actions)
            dt = time.perf_counter() - t0
            if compile_s is None:
                compile_s = dt  # first call: compilation + first solve
                bridge.reset_stats()
            else:
                lat.append(dt)
            obs, state, _, _, _ = step(k, state, actions[0], params)
    stats = bridge.stats()
    bridge.close()
    return {
        "calls": len(lat),
        "first_call_s": compile_s,
        "call": harness.summarize(lat),
        "p95_s": float(np.percentile(lat, 95)),
        "host_call_median_s": float(np.median(stats["host_call_s"])),
        "solve_median_s": float(np.median(stats["solve_s"])),
        "status": stats["status"],
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument("--run", default=None, help="run directory of a trained agent")
    args = p.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = SIZES[size]
    from mpcpearl_jax import load_policy
    from mpcpearl_jax.errors import CheckpointError, RunDirError

    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(args.run) if args.run else Path(tmp) / "run"
        if not args.run:
            save_untrained_run(run_dir, sz["preset"])
        t0 = time.perf_counter()
        try:
            policy = load_policy(run_dir)
        except (CheckpointError, RunDirError, OSError, ValueError, TypeError) as e:
            harness.fail(f"--run {run_dir}: {harness.error_text(e)}")  # before anything is timed
        load_s = time.perf_counter() - t0
    rows = policy_timings(policy, sz)
    mpc = mpc_timings(policy, sz)
    mpc_us = mpc["call"]["median_s"] * 1e6
    rows.append(
        {
            "call": "MPC (GP + SQP via callback)",
            "batch": 1,
            "latency_us": mpc_us,
            "per_row_us": mpc_us,
            "first_call_s": mpc["first_call_s"],
        }
    )
    act1 = rows[0]["latency_us"]
    for r in rows:
        r["mpc_over_this"] = mpc_us / r["latency_us"]
    harness.print_table(
        rows,
        ["call", "batch", "latency_us", "per_row_us", "mpc_over_this", "first_call_s"],
        f"Policy vs MPC latency ({size})",
    )
    summary = {
        "load_policy_s": load_s,
        "mpc_over_policy_batch1": mpc_us / act1,
        "mpc_p95_us": mpc["p95_s"] * 1e6,
        "targets": {
            "policy_100x_faster_than_mpc": mpc_us / act1 >= 100,
            "batch1_policy_under_100us": act1 < 100,
        },
    }
    print(
        f"MPC call median {mpc_us:,.0f} us (p95 {summary['mpc_p95_us']:,.0f} us); "
        f"policy batch 1 {act1:.1f} us: {summary['mpc_over_policy_batch1']:.0f}x",
        flush=True,
    )
    results = {"rows": rows, "mpc": mpc, "summary": summary}
    config = {
        "size": size,
        **sz,
        "threads": threads,
        "run": args.run or "untrained (temporary)",
        "pearl": policy.config.to_dict()["pearl"],
        "mpc": policy.config.mpc.to_dict(),
    }
    harness.write_record("policy_latency", config, results, args.out)
    return results


if __name__ == "__main__":
    main()
