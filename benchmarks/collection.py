"""Collection without the MPC (eps = 0) against a bare `lax.scan` of the env and the policy.

At the main command's shapes (`python -m experiments.restaurant`: the `default` preset on the
restaurant tasks, horizon 80, 2 x 64 networks, the observation options), `--seeds` seeds:

  * collector: `collection.make_collector` as the trainer builds it for MPC infusion, with the
    MPC bridge of the preset's `mpc` config, called with eps = 0, jitted; one call collects one
    episode on each row (the rows of a prior or posterior phase: tasks_per_iteration x episodes
    per seed, and those of the initial collection: every training task);
  * collector without bridge: the same at eps = 0 with no bridge (what `Trainer` builds for
    eps = 0);
  * bare scan: one jitted `lax.scan` over the horizon of `vmap(env.step)` and the policy's
    `nets.act` (vmapped over seeds, as the collector does) on the same rows, keeping the
    transitions (obs, action, reward, next obs) that any collection must return, nothing else.

Compilation is excluded (reported apart). The three are timed in turns, sample by sample (each
sample several calls), so that load from other processes hits them alike; medians, quartiles and
the ratio collector / bare scan (target <= 1.3) are printed and written with the command line to
OUT/collection.json (OUT/collection-seeds<N>.json for --seeds N > 1).

    python -m benchmarks.collection [--tiny | --full] [--seeds N] [--out DIR] [--threads N]
"""

from __future__ import annotations

import sys
from typing import Any

from benchmarks import harness

SIZES: dict[str, dict[str, Any]] = {
    # tiny: a short horizon, only so that the script runs in seconds
    "tiny": dict(horizon=5, repeats=2, sample_s=0.02, initial=False),
    "default": dict(horizon=None, repeats=9, sample_s=0.4, initial=True),
    "full": dict(horizon=None, repeats=21, sample_s=1.0, initial=True),
}
TARGET_RATIO = 1.3


def build(seeds: int, horizon: int | None):
    """(config, env, nets, bridge, policy params [S], training tasks) of the main command."""
    import jax

    from mpcpearl_jax.config import resolve
    from mpcpearl_jax.envs import make_env, tasks_for
    from mpcpearl_jax.mpc import make_mpc_bridge
    from mpcpearl_jax.pearl import Networks, init_learner

    cfg = resolve("default", "restaurant").replace(seeds=seeds)
    overrides = dict(cfg.env_overrides)
    if horizon is not None:
        overrides["horizon"] = horizon
    cfg = cfg.replace(env_overrides=overrides)
    env = make_env(cfg.env, **cfg.env_overrides)
    tasks = tasks_for(cfg, "train", config=env.config)
    nets = Networks(cfg.pearl, env.obs_dim(tasks), env.action_dim)
    keys = jax.random.split(jax.random.PRNGKey(cfg.seed), seeds)
    params = jax.vmap(lambda k: init_learner(k, nets).params["policy"])(keys)
    return cfg, env, nets, make_mpc_bridge(env, cfg.mpc), params, tasks


def make_bare_scan(env, nets):
    """Jitted `run(key, policy_params [S], z [S, R, L], tasks [S, R]) -> transitions [T, S*R]`:
    reset, then a `lax.scan` over the horizon of the policy's action and `vmap(env.step)`."""
    import jax

    def run(key, policy_params, z, tasks):
        s, r = z.shape[:2]
        flat = jax.tree_util.tree_map(lambda x: x.reshape((s * r, *x.shape[2:])), tasks)
        obs0, state0 = jax.vmap(env.reset)(jax.random.split(key, s * r), flat)

        def body(carry, k):
            obs, state = carry
            keys = jax.random.split(k, s)
            act = jax.vmap(nets.act)(policy_params, obs.reshape(s, r, -1), z, keys)
            action = act.reshape(s * r, -1)
            nobs, nstate, rew, _, _ = jax.vmap(env.step)(
                jax.random.split(k, s * r), state, action, flat
            )
            return (nobs, nstate), (obs, action, rew, nobs)

        steps = jax.random.split(key, env.config.horizon)
        return jax.lax.scan(body, (obs0, state0), steps)[1]

    return jax.jit(run)


def measure(impls: dict[str, Any], args: tuple, repeats: int, sample_s: float) -> dict[str, Any]:
    """Compile each jitted impl on args, then time them in turns: raw samples and summaries."""
    import time

    import jax

    compiled, out = {}, {}
    for name, fn in impls.items():
        compiled[name], compile_s = harness.timed(lambda fn=fn: fn.lower(*args).compile())
        jax.block_until_ready(compiled[name](*args))  # warm-up, not timed
        _, once = harness.timed(lambda n=name: jax.block_until_ready(compiled[n](*args)))
        out[name] = {"compile_s": compile_s, "inner": harness.calls_for(once, sample_s)}
    raw: dict[str, list[float]] = {name: [] for name in impls}
    order = list(impls)
    for i in range(repeats):
        for name in order if i % 2 == 0 else order[::-1]:
            fn, inner = compiled[name], out[name]["inner"]
            t0 = time.perf_counter()
            for _ in range(inner):
                res = fn(*args)
            jax.block_until_ready(res)
            raw[name].append((time.perf_counter() - t0) / inner)
    for name in impls:
        out[name].update(harness.summarize(raw[name]))
    return out


def bench_shape(label: str, rows: int, env, nets, bridge, params, tasks, cfg) -> dict[str, Any]:
    """The three impls on `rows` rows per seed; seconds per collection and the ratios."""
    import jax
    import jax.numpy as jnp

    from mpcpearl_jax import collection as collect_lib

    seeds = int(jax.tree_util.tree_leaves(params)[0].shape[0])
    n = int(tasks.start.shape[0])
    ids = (jnp.arange(seeds * rows) % n).reshape(seeds, rows)
    row_tasks = collect_lib.rows_of(tasks, ids)
    z = jax.random.normal(jax.random.PRNGKey(1), (seeds, rows, nets.cfg.latent_dim))
    args = jax.device_put((jax.random.PRNGKey(0), params, z, row_tasks))
    impls = {
        "collector": jax.jit(collect_lib.make_collector(env, nets, bridge, 0.0)),
        "collector_no_bridge": jax.jit(collect_lib.make_collector(env, nets, None, 0.0)),
        "bare_scan": make_bare_scan(env, nets),
    }
    timing = measure(impls, args, cfg["repeats"], cfg["sample_s"])
    horizon = env.config.horizon
    bare = timing["bare_scan"]["median_s"]
    row = {
        "shape": label,
        "seeds": seeds,
        "rows_per_seed": rows,
        "horizon": horizon,
        "timing": timing,
    }
    for name, t in timing.items():
        row[f"{name}_ms"] = 1e3 * t["median_s"]
        row[f"{name}_ms_per_step"] = 1e3 * t["median_s"] / horizon
        row[f"{name}_env_steps_per_s"] = seeds * rows * horizon / t["median_s"]
    row["ratio"] = timing["collector"]["median_s"] / bare
    row["ratio_no_bridge"] = timing["collector_no_bridge"]["median_s"] / bare
    # the ratio's spread: from the best to the worst pairing of the two quartile ranges
    row["ratio_p25_p75"] = [
        timing["collector"]["p25_s"] / timing["bare_scan"]["p75_s"],
        timing["collector"]["p75_s"] / timing["bare_scan"]["p25_s"],
    ]
    return row


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument(
        "--seeds", type=int, default=1, help="seeds in one program (8: the GPU recipe's)"
    )
    args = p.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = SIZES[size]
    import jax

    cfg, env, nets, bridge, params, tasks = build(args.seeds, sz["horizon"])
    tc = cfg.train
    shapes = [("phase", tc.tasks_per_iteration * max(tc.prior_episodes, tc.posterior_episodes))]
    if sz["initial"]:
        shapes.append(("initial", int(tasks.start.shape[0]) * tc.initial_episodes))
    rows = [bench_shape(label, r, env, nets, bridge, params, tasks, sz) for label, r in shapes]
    bridge.close()

    cols = [
        "shape",
        "seeds",
        "rows_per_seed",
        "collector_ms",
        "collector_no_bridge_ms",
        "bare_scan_ms",
        "collector_ms_per_step",
        "ratio",
    ]
    harness.print_table(
        rows, cols, f"eps-0 collection vs. bare lax.scan ({jax.default_backend()}, {size})"
    )
    worst = max(r["ratio"] for r in rows)
    summary = {
        "max_ratio": worst,
        "target_ratio": TARGET_RATIO,
        "targets": {f"ratio<={TARGET_RATIO}": worst <= TARGET_RATIO},
    }
    ratios = ", ".join(f"{r['shape']} {r['ratio']:.2f}" for r in rows)
    met = "met" if worst <= TARGET_RATIO else "not met"
    print(f"collector / bare scan: {ratios} (target <= {TARGET_RATIO}: {met})", flush=True)
    config = {
        "size": size,
        **sz,
        "command": " ".join(
            ["python -m benchmarks.collection", *(sys.argv[1:] if argv is None else argv)]
        ),
        "backend": jax.default_backend(),
        "threads": threads,
        "preset": "default",
        "env": cfg.env,
        "seeds": args.seeds,
        "horizon": env.config.horizon,
        "hidden": cfg.pearl.hidden,
        "eps": 0.0,
    }
    name = "collection" if args.seeds == 1 else f"collection-seeds{args.seeds}"
    harness.write_record(name, config, {"shapes": rows, "summary": summary}, args.out)
    return {"shapes": rows, "summary": summary}


if __name__ == "__main__":
    main()
