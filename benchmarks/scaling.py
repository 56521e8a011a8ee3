"""Seeds sharded over devices: aggregate gradient steps/s and env steps/s for 1, 2, 4 devices at
an equal total number of seeds (`ExperimentConfig.devices`, `mpcpearl_jax.distributed`).

Each device count runs in its own process: on a CPU the devices are forced host devices
(XLA_FLAGS=--xla_force_host_platform_device_count=N), which share the machine's cores, so the
figures measure the overhead of sharding (partitioned programs, per-device dispatch), not a
speed-up; on a machine with N accelerators (`--real`) they are the real devices. Each run
builds the trainer, runs one iteration to compile everything (reported as `first_iteration_s`),
then times `--iterations` iterations: env steps/s = seeds x env steps of an iteration / its
collection time, gradient steps/s = seeds x updates / its update time (medians). eps = 0 (pure
JAX; the MPC's host solves do not depend on the device count).

    python -m benchmarks.scaling [--tiny | --full] [--out DIR] [--devices 1 2 4] [--real]
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks import harness
from mpcpearl_jax.cli.stopping import stops_with

SEEDS = 4
SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(updates=5, iterations=2, hidden=(16, 16), tasks_per_iteration=4),
    "default": dict(updates=100, iterations=4, hidden=(128, 128, 128), tasks_per_iteration=8),
    "full": dict(updates=500, iterations=4, hidden=(128, 128, 128), tasks_per_iteration=8),
}


def build_config(sz: dict[str, Any], devices: int):
    from mpcpearl_jax.config import preset
    from mpcpearl_jax.mpc.config import MPCConfig

    # the CPU schedule and networks with the paper's algorithm (the former `cpu-paper` preset):
    # `cpu-explore` without its extensions and observation options
    base = preset("cpu-explore").replace(mpc=MPCConfig(), env_overrides={})
    pearl = base.pearl.replace(hidden=sz["hidden"], encoder_hidden=sz["hidden"], layer_norm=False)
    train = dataclasses.replace(
        base.train,
        redraw_behaviours=False,
        explore_start_share=0.0,
        eps=0.0,
        updates_per_iteration=sz["updates"],
        tasks_per_iteration=sz["tasks_per_iteration"],
        rl_capacity=2000,
        eval_interval=0,
    )
    return base.replace(
        seeds=SEEDS,
        devices=devices,
        pearl=pearl,
        train=train,
        task_options={"train_behaviours": 1},  # 8 training tasks
    )


def child(size: str, devices: int, out: Path) -> None:
    """One device count, in this process (the device count is fixed when JAX starts)."""
    import jax

    from mpcpearl_jax.training.trainer import Trainer

    sz = SIZES[size]
    cfg = build_config(sz, devices)
    t0 = time.perf_counter()
    trainer = Trainer(cfg)
    state = trainer.init_state()
    state, _ = trainer.iteration(state)  # iteration 0 + 1: compiles every phase
    first = time.perf_counter() - t0
    collect, update = [], []
    for _ in range(sz["iterations"]):
        state, log = trainer.iteration(state)
        collect.append(log["collect_s"])
        update.append(log["update_s"])
    jax.block_until_ready(state)
    steps = trainer.steps_per_iteration()
    c, u = statistics.median(collect), statistics.median(update)
    res = {
        "devices": 1 if trainer.mesh is None else int(trainer.mesh.devices.size),
        "device_kind": str(jax.devices()[0].platform),
        "seeds": SEEDS,
        "seeds_per_device": SEEDS // (1 if trainer.mesh is None else trainer.mesh.devices.size),
        "first_iteration_s": first,
        "collect_s": collect,
        "update_s": update,
        "env_steps_per_iteration": SEEDS * steps,
        "grad_steps_per_iteration": SEEDS * cfg.train.updates_per_iteration,
        "env_steps_per_s": SEEDS * steps / c,
        "grad_steps_per_s": SEEDS * cfg.train.updates_per_iteration / u,
        "loadavg_end": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    out.write_text(json.dumps(res))


@stops_with("interrupted; the scaling record is not written")
def main(argv: list[str] | None = None) -> None:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--real", action="store_true", help="use the machine's own devices")
    p.add_argument("--child", nargs=2, metavar=("DEVICES", "RESULT"), help=argparse_hidden())
    args = p.parse_args(argv)
    size = harness.size_of(args)
    if args.child:
        child(size, int(args.child[0]), Path(args.child[1]))
        return
    threads = harness.configure_threads(args.threads)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for d in args.devices:
            env = dict(os.environ)
            if not args.real:
                flags = env.get("XLA_FLAGS", "")
                env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={d}".strip()
                env["JAX_PLATFORMS"] = "cpu"
            result = Path(tmp) / f"d{d}.json"
            cmd = [sys.executable, "-m", "benchmarks.scaling", "--child", str(d), str(result)]
            cmd += [] if size == "default" else [f"--{size}"]
            root = Path(__file__).resolve().parents[1]
            subprocess.run(cmd, env=env, cwd=root, check=True)
            rows.append(json.loads(result.read_text()))
    base = rows[0]
    for r in rows:
        r["env_vs_1"] = r["env_steps_per_s"] / base["env_steps_per_s"]
        r["grad_vs_1"] = r["grad_steps_per_s"] / base["grad_steps_per_s"]
    cols = [
        "devices",
        "seeds_per_device",
        "grad_steps_per_s",
        "grad_vs_1",
        "env_steps_per_s",
        "env_vs_1",
        "first_iteration_s",
    ]
    harness.print_table(rows, cols, title=f"{SEEDS} seeds over 1, 2, 4 devices ({size})")
    config = {
        "size": size,
        "seeds": SEEDS,
        **{k: list(v) if isinstance(v, tuple) else v for k, v in SIZES[size].items()},
        "forced_host_devices": not args.real,
        "threads": threads,
    }
    harness.write_record("scaling", config, rows, args.out)


def argparse_hidden() -> str:
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    main()
