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

    python -m benchmarks.learner_sizes [--tiny] [--out DIR] [--threads N]
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


class Point:
    """One learner size's jitted update, compiled, on a fixed batch."""

    def __init__(self, width: int, layers: int, tasks: int):
        import jax
        import jax.numpy as jnp

        from mpcpearl_jax.config import preset
        from mpcpearl_jax.pearl import Networks, Transitions, init_learner, make_update

        self.jax = jax
        hidden = (width,) * layers
        self.cfg = dataclasses.replace(
            preset("default").pearl, hidden=hidden, encoder_hidden=hidden, meta_batch=tasks
        )
        nets = Networks(self.cfg, OBS_DIM, ACTION_DIM)
        nb = random_numpy_batch(self.cfg, seed=0)
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


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = harness.common_parser(__doc__.splitlines()[0])
    args = parser.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = SIZES[size]
    points = {f"{w}x{layers}, {t} tasks": Point(w, layers, t) for w, layers, t in sz["points"]}
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
    for (name, s), (w, layers, t) in zip(stats.items(), sz["points"], strict=True):
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
        "baseline": base_name,
        "steps_per_sample": sz["steps_per_sample"],
        "rounds": sz["rounds"],
        "pearl_default": dataclasses.asdict(points[base_name].cfg),
        "threads": threads,
        "data": "fixed random batch per point (no replay sampling timed)",
    }
    results = {"rows": rows, "raw": stats}
    harness.write_record("learner_sizes", config, results, args.out)
    return results


if __name__ == "__main__":
    main()
