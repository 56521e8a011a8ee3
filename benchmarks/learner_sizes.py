"""Seconds per gradient step of the main command's learner at other widths and tasks per step.

The `default` preset's PEARL update (2 x 64 networks, 4 tasks per gradient step, LayerNorm
critics, automatic entropy tuning) against the same update with other hidden widths (networks
and encoder alike) and meta-batch sizes, on the same fixed random batches (replay sampling not
timed), samples interleaved round by round so that load from other processes hits every point
alike. Each point's cost is given relative to `default`'s, and with it the iteration count that
gives its updates the time of `default`'s 75 iterations; collection (the same for every point)
is not in that count, so it is an upper bound: with collection taking C seconds and the update U
per iteration for `default`, a point costing r times as much per step gets
75 (C + U) / (C + r U) iterations for the same training time (results/restaurant/plateau/
width-cost.json measures C and U).

With `--encoders` the points are instead `default`'s learner on its own observation (the
restaurant's, with `default`'s observation options), and the same learner with a crowd encoder
(`pearl.crowd_encoder` "attention", "deepsets" or "sarl", which add the people's presence to the
observation) without and with the forecast (`env.observe_forecast` 5, `env.forecast_stride` 2),
at several widths, one encoder per network or one shared by the critics (`pearl.crowd_shared`),
the tables pooled or as plain features (`pearl.crowd_static`), "sarl" pools (a scalar score per
person) with one per-entity layer (`pearl.crowd_layers`): the price of each encoder per
gradient step, for comparing it with `default` at equal wall time.

    python -m benchmarks.learner_sizes [--tiny] [--encoders] [--out DIR] [--threads N]
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

from benchmarks import harness
from benchmarks.pearl_step import ACTION_DIM, OBS_DIM, random_numpy_batch

# (hidden width, layers, tasks per gradient step); the first is `default`'s learner
POINTS: tuple[tuple[int, int, int], ...] = (
    (64, 2, 4),
    (64, 2, 8),
    (96, 2, 6),
    (128, 2, 4),
    (128, 2, 8),
    (128, 3, 8),  # the recommended recipe's networks and tasks per step
)
SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(points=((16, 2, 2), (32, 2, 2)), steps_per_sample=2, rounds=2),
    "default": dict(points=POINTS, steps_per_sample=50, rounds=5),
    "full": dict(points=POINTS, steps_per_sample=100, rounds=10),
}
DEFAULT_ITERATIONS = 75
# (crowd encoder, forecast points, crowd_dim, shared, static, per-entity layers) of the
# --encoders points, at `default`'s sizes
ENCODERS: tuple[tuple[str, int, int, bool, str, int], ...] = (
    ("none", 0, 64, False, "pool", 2),
    ("attention", 5, 64, False, "pool", 2),
    ("attention", 5, 16, False, "pool", 2),
    ("attention", 5, 64, True, "pool", 2),
    ("attention", 5, 16, True, "pool", 2),
    ("attention", 5, 16, True, "flat", 2),
    ("deepsets", 5, 16, True, "flat", 2),
    ("deepsets", 5, 64, True, "flat", 1),
    ("sarl", 5, 32, True, "pool", 1),
    ("sarl", 5, 32, True, "flat", 1),
    ("sarl", 5, 64, True, "flat", 1),
)
TINY_ENCODERS = (ENCODERS[0], ENCODERS[2], ENCODERS[8])


class Point:
    """One learner size's jitted update, compiled, on a fixed batch."""

    def __init__(
        self,
        width: int,
        layers: int,
        tasks: int,
        encoder: str | None = None,
        forecast: int = 0,
        crowd_dim: int = 64,
        shared: bool = False,
        static: str = "pool",
        entity_layers: int = 2,
    ):
        """`encoder` None: the fixed benchmark observation; "none" or "attention": the
        restaurant's observation under `default`'s options (+ presence and `forecast` points
        with the crowd encoder)."""
        import jax
        import jax.numpy as jnp
        import numpy as np

        from mpcpearl_jax.config import preset
        from mpcpearl_jax.pearl import Networks, Transitions, init_learner, make_update

        self.jax = jax
        hidden = (width,) * layers
        self.cfg = dataclasses.replace(
            preset("default").pearl,
            hidden=hidden,
            encoder_hidden=hidden,
            meta_batch=tasks,
            crowd_encoder=encoder or "none",
            crowd_dim=crowd_dim,
            crowd_heads=min(4, crowd_dim // 4),
            crowd_shared=shared,
            crowd_static=static,
            crowd_layers=entity_layers,
        )
        if encoder is None:
            nets = Networks(self.cfg, OBS_DIM, ACTION_DIM)
            nb = random_numpy_batch(self.cfg, seed=0)
        else:
            nets, nb = _restaurant_learner(self.cfg, forecast)
            nb = {k: np.asarray(v) for k, v in nb.items()}
        self.batch = Transitions(
            **{k: jnp.asarray(v) for k, v in nb.items() if k in Transitions._fields}
        )
        self.context = jnp.asarray(nb["context"])
        self.state = init_learner(jax.random.key(0), nets)
        self.keys = list(jax.random.split(jax.random.key(1), 64))
        lowered = make_update(nets).lower(self.state, self.batch, self.context, self.keys[0])
        self.update, self.compile_s = harness.timed(lowered.compile)
        self.i = 0

    def steps(self, n: int) -> None:
        for _ in range(n):
            self.state, _ = self.update(
                self.state, self.batch, self.context, self.keys[self.i % len(self.keys)]
            )
            self.i += 1
        self.jax.block_until_ready(self.state)


def _restaurant_learner(cfg, forecast: int):
    """(Networks, random batch) on the restaurant's observation under `default`'s options, with
    the people's presence and `forecast` points when `cfg` has a crowd encoder."""
    import numpy as np

    from mpcpearl_jax.config import preset
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.pearl import Networks

    overrides = dict(preset("default").env_overrides)
    if cfg.crowd_encoder != "none":
        overrides.update(observe_presence=True, observe_forecast=forecast, forecast_stride=2)
    env = make_env("restaurant", **overrides)
    tasks = make_tasks("restaurant", "val", 1, config=env.config)
    obs_dim = env.obs_dim(tasks)
    nets = Networks(cfg, obs_dim, ACTION_DIM, env.obs_layout(tasks))
    nb = random_numpy_batch(cfg, seed=0)
    rng = np.random.default_rng(1)
    mb, b, c = cfg.meta_batch, cfg.batch_size, cfg.context_size
    for k, shape in (("obs", (mb, b, obs_dim)), ("next_obs", (mb, b, obs_dim))):
        nb[k] = rng.uniform(-1, 1, shape).astype(np.float32)
    nb["context"] = rng.uniform(-1, 1, (mb, c, nets.context_dim)).astype(np.float32)
    return nets, nb


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = harness.common_parser(__doc__.split("\n\n")[0])
    parser.add_argument(
        "--encoders",
        action="store_true",
        help="default's learner with and without the crowd encoder, on the restaurant's obs",
    )
    args = parser.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = dict(SIZES[size])
    if args.encoders:
        w, layers, t = sz["points"][0]
        encoders = TINY_ENCODERS if size == "tiny" else ENCODERS
        sz["points"] = tuple((w, layers, t, *e) for e in encoders)
        names = [
            f"crowd {enc}"
            + (f" (dim {d})" if enc != "none" else "")
            + (f" + forecast {f}" if f else "")
            + (", shared" if shared else "")
            + (", tables flat" if enc != "none" and static == "flat" else "")
            + (f", {layers} layer" if enc in ("deepsets", "sarl") and layers != 2 else "")
            for enc, f, d, shared, static, layers in encoders
        ]
    else:
        names = [f"{w}x{layers}, {t} tasks" for w, layers, t in sz["points"]]
    points = {n: Point(*pt) for n, pt in zip(names, sz["points"], strict=True)}
    for p in points.values():
        p.steps(1)
    raw: dict[str, list[float]] = {k: [] for k in points}
    for _ in range(sz["rounds"]):
        for name, p in points.items():
            t0 = time.perf_counter()
            p.steps(sz["steps_per_sample"])
            raw[name].append((time.perf_counter() - t0) / sz["steps_per_sample"])
    stats = {k: harness.summarize(v) for k, v in raw.items()}
    base_name = next(iter(points))
    base = stats[base_name]["median_s"]
    rows = []
    for (name, s), (w, layers, t, *_) in zip(stats.items(), sz["points"], strict=True):
        ratio = s["median_s"] / base
        rows.append(
            {
                "learner": name,
                "width": w,
                "layers": layers,
                "tasks_per_step": t,
                "ms_per_step": 1e3 * s["median_s"],
                "p25_ms": 1e3 * s["p25_s"],
                "p75_ms": 1e3 * s["p75_s"],
                "x_default": ratio,
                "iterations_at_equal_update_time": DEFAULT_ITERATIONS / ratio,
                "compile_s": points[name].compile_s,
            }
        )
    harness.print_table(
        rows,
        [
            "learner",
            "ms_per_step",
            "p25_ms",
            "p75_ms",
            "x_default",
            "iterations_at_equal_update_time",
        ],
        f"PEARL gradient step of the main command's learner and other sizes ({size}, "
        f"{threads['threads']} threads; first row = baseline)",
    )
    config = {
        "size": size,
        "points": [list(p) for p in sz["points"]],
        "encoders": args.encoders,
        "baseline": base_name,
        "steps_per_sample": sz["steps_per_sample"],
        "rounds": sz["rounds"],
        "pearl_default": dataclasses.asdict(points[base_name].cfg),
        "threads": threads,
        "data": "fixed random batch per point (no replay sampling timed)",
    }
    results = {"rows": rows, "raw": stats}
    name = "learner_sizes-encoders" if args.encoders else "learner_sizes"
    harness.write_record(name, config, results, args.out)
    return results


if __name__ == "__main__":
    main()
