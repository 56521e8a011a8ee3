"""GrBAL planner latency per env step: one inner SGD step on the last M transitions plus MPPI on
the adapted model (the work of every GrBAL step in collection and meta-test), at batch 1 and
batched over the restaurant test tasks; and the plan alone (model fixed).

Sizes: the `cpu` preset (3 x 128 model, N = 128 sequences, 1 MPPI iteration) and the paper's
GrBAL table (3 x 256, N = 256, 2 iterations), horizon 10, untrained weights (latency does not
depend on them). Compilation is excluded and reported as first_call_s.

    python -m benchmarks.grbal_planner [--tiny | --full] [--out DIR] [--threads N]
"""

from __future__ import annotations

from typing import Any

from benchmarks import harness

SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(presets=("smoke",), batches=(1, 4), repeats=3, sample_s=0.02),
    "default": dict(presets=("cpu", "paper"), batches=(1, 24), repeats=7, sample_s=0.3),
    "full": dict(presets=("cpu", "paper"), batches=(1, 24, 120), repeats=15, sample_s=1.0),
}


def planner_rows(preset_name: str, batches, cfg: dict[str, Any]) -> list[dict[str, Any]]:
    import jax
    import jax.numpy as jnp

    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.grbal.config import preset
    from mpcpearl_jax.grbal.model import DynamicsModel, identity_normalizer, layout_of
    from mpcpearl_jax.grbal.planner import Planner

    g = preset(preset_name)
    env = make_env("restaurant")
    tasks = make_tasks("restaurant", "test")
    layout = layout_of(env, tasks)
    model = DynamicsModel(layout, g.hidden)
    params = model.init(jax.random.PRNGKey(0))
    norm = identity_normalizer(layout)
    planner = Planner.from_config(model, env.config, g)
    m, od = g.past, layout.obs_dim

    def step(obs, hist, task, key, adapt: bool):
        p = params
        if adapt:
            h_o, h_a, h_n = hist
            p = model.adapt(params, norm, h_o, h_a, h_n, g.inner_lr)
        return planner.plan(p, norm, obs, planner.initial_mean(), task, key)

    rows = []
    for batch in batches:
        tb = jax.tree_util.tree_map(lambda x, b=batch: x[jnp.arange(b) % x.shape[0]], tasks)
        obs = jax.vmap(lambda t: env.reset(jax.random.PRNGKey(0), t)[0])(tb)
        k = jax.random.PRNGKey(1)
        hist = (
            jax.random.uniform(k, (batch, m, od), minval=-1, maxval=1),
            jax.random.uniform(k, (batch, m, 2), minval=-1, maxval=1),
            jax.random.uniform(k, (batch, m, od), minval=-1, maxval=1),
        )
        keys = jax.random.split(k, batch)
        for adapt in (True, False):
            fn = jax.jit(jax.vmap(lambda o, h, t, kk, a=adapt: step(o, h, t, kk, a)))
            args = (obs, hist, tb, keys)
            call = lambda fn=fn, args=args: fn(*args)  # noqa: E731
            _, first = harness.timed(lambda call=call: jax.block_until_ready(call()))
            _, once = harness.timed(lambda call=call: jax.block_until_ready(call()))
            t = harness.time_fn(
                call,
                repeats=cfg["repeats"],
                block=jax.block_until_ready,
                inner=harness.calls_for(once, cfg["sample_s"]),
            )
            rows.append(
                {
                    "preset": preset_name,
                    "model": "x".join(map(str, g.hidden)),
                    "samples": g.num_samples,
                    "mppi_iterations": g.mppi_iterations,
                    "what": "adapt + plan" if adapt else "plan only",
                    "batch": batch,
                    "latency_ms": t["median_s"] * 1e3,
                    "per_env_ms": t["median_s"] * 1e3 / batch,
                    "first_call_s": first,
                    "timing": t,
                }
            )
    return rows


def main(argv: list[str] | None = None) -> None:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    args = p.parse_args(argv)
    size = harness.size_of(args)
    threads = harness.configure_threads(args.threads)
    cfg = SIZES[size]
    rows = []
    for name in cfg["presets"]:
        rows += planner_rows(name, cfg["batches"], cfg)
    harness.print_table(
        rows,
        ["preset", "model", "samples", "mppi_iterations", "what", "batch", "latency_ms"]
        + ["per_env_ms", "first_call_s"],
        title="GrBAL planner step (restaurant, horizon 10)",
    )
    harness.write_record("grbal_planner", {"size": size, **threads, **cfg}, rows, args.out)


if __name__ == "__main__":
    main()
