"""Pipelined iterations against Algorithm 1's order: the main command's iterations, side by side.

Two trainers of the same preset and seed, one with `train.pipeline` (the episodes of iteration
k + 1 collected beside the gradient steps of iteration k), one without, take turns iteration by
iteration in one process (which goes first alternates), so both see the same machine and load.
Per iteration: the wall time of `Trainer.iteration` (evaluation is not part of it), its
collection and update seconds. The record gives both trainers' summed wall time over iterations
3 to the last (the first two compile and fill the buffers), their ratio and the saving
(1 - ratio); the target on a 2-core CPU is a saving of at least 20 % at the main command's
settings (`default` preset, 75 iterations, one seed).

    python -m benchmarks.pipeline [--tiny] [--preset NAME] [--iterations N] [--seeds S]
                                  [--out DIR] [--threads N]
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any

from benchmarks import harness

FROM = 3  # the first timed iteration: 1 compiles and fills the buffers, 2 compiles the rest
TARGET_SAVING = 0.20


def build(preset_name: str, iterations: int, seeds: int, pipeline: bool, tiny: bool):
    from mpcpearl_jax.config import preset
    from mpcpearl_jax.training.trainer import Trainer

    cfg = preset(preset_name)
    train = dataclasses.replace(cfg.train, iterations=iterations, pipeline=pipeline)
    if tiny:
        train = dataclasses.replace(train, updates_per_iteration=5)
    return Trainer(cfg.replace(seeds=seeds, train=train))


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument("--preset", default=None, help="default: `default` (smoke at --tiny)")
    p.add_argument("--iterations", type=int, default=None, help="default: the preset's")
    p.add_argument("--seeds", type=int, default=1)
    args = p.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    import jax

    name = args.preset or ("smoke" if args.tiny else "default")
    from mpcpearl_jax.config import preset

    n = args.iterations or (FROM + 1 if args.tiny else preset(name).train.iterations)
    if n < FROM:
        p.error(f"--iterations must be at least {FROM}")
    trainers = {
        "serial": build(name, n, args.seeds, False, args.tiny),
        "pipeline": build(name, n, args.seeds, True, args.tiny),
    }
    states = {k: t.init_state() for k, t in trainers.items()}
    rows: dict[str, list[dict[str, float]]] = {k: [] for k in trainers}
    order = list(trainers)
    try:
        for i in range(1, n + 1):
            for k in order if i % 2 else order[::-1]:
                t0 = time.perf_counter()
                states[k], log = trainers[k].iteration(states[k])
                jax.block_until_ready(states[k])
                wall = time.perf_counter() - t0
                rows[k].append(
                    {
                        "iteration": i,
                        "wall_s": wall,
                        "collect_s": log["collect_s"],
                        "update_s": log["update_s"],
                        "mpc_rows": log.get("mpc_rows", 0),
                        "mpc_solve_s": log.get("mpc_solve_s", 0.0),
                    }
                )
            if i % 10 == 0 or i == n:
                done = {k: f"{rows[k][-1]['wall_s']:.2f} s" for k in order}
                print(f"iteration {i}/{n}: {done}", flush=True)
    finally:
        for t in trainers.values():
            t.close()

    def part(k: str, field: str) -> list[float]:
        return [r[field] for r in rows[k] if r["iteration"] >= FROM]

    total = {k: sum(part(k, "wall_s")) for k in order}
    ratio = total["pipeline"] / total["serial"]
    results = {
        "iterations": n,
        "timed_from": FROM,
        "total_wall_s": total,
        "median_wall_s": {k: harness.summarize(part(k, "wall_s"))["median_s"] for k in order},
        "median_collect_s": {k: harness.summarize(part(k, "collect_s"))["median_s"] for k in order},
        "median_update_s": {k: harness.summarize(part(k, "update_s"))["median_s"] for k in order},
        "ratio_pipeline_to_serial": ratio,
        "saving": 1.0 - ratio,
        "target_saving": TARGET_SAVING,
        "target_met": 1.0 - ratio >= TARGET_SAVING,
        "loadavg_after": list(os.getloadavg()),
        "rows": rows,
    }
    harness.print_table(
        [
            {
                "trainer": k,
                f"wall, iterations {FROM}-{n} (s)": total[k],
                "median iteration (s)": results["median_wall_s"][k],
                "median collect (s)": results["median_collect_s"][k],
                "median update (s)": results["median_update_s"][k],
            }
            for k in order
        ],
        [
            "trainer",
            f"wall, iterations {FROM}-{n} (s)",
            "median iteration (s)",
            "median collect (s)",
            "median update (s)",
        ],
    )
    print(
        f"pipeline / serial: {ratio:.3f} (saving {100 * (1 - ratio):.1f} %, "
        f"target >= {100 * TARGET_SAVING:.0f} %: {'met' if results['target_met'] else 'not met'})"
    )
    config = {
        "preset": name,
        "seeds": args.seeds,
        "iterations": n,
        "size": harness.size_of(args),
        "threads": threads,
        "command": "python -m benchmarks.pipeline"
        + (" --tiny" if args.tiny else "")
        + (f" --preset {args.preset}" if args.preset else "")
        + (f" --iterations {args.iterations}" if args.iterations else "")
        + (f" --seeds {args.seeds}" if args.seeds != 1 else ""),
    }
    record = "pipeline" + (f"-seeds{args.seeds}" if args.seeds != 1 else "")
    path = harness.write_record(record, config, results, args.out)
    print(f"record: {path}")
    return results


if __name__ == "__main__":
    main()
