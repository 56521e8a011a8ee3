"""Host memory of a training run: the buffers of 120 tasks at the paper's sizes, and scaling.

Measured two ways, each in a fresh child process (peak RSS only grows within a process):
  * array bytes: `nbytes` summed over the `TrainState` leaves (RL buffers, encoder buffers,
    learner = params + target V + Adam moments), i.e. what the state itself holds;
  * resident memory from /proc/self/status: VmRSS after `import jax` + env setup (baseline),
    after `Trainer.init_state()`, and the peak (VmHWM) after the initial collection and one
    iteration, which includes XLA's compilation and temporaries. tracemalloc is not used: JAX
    allocates its buffers outside Python's allocator.

Runs: the `paper` preset (method §7 networks, per-task RL capacity and encoder capacity of the
trainer) with MPC off (eps = 0: MPC adds no buffers) and a shortened update phase (buffer sizes
unchanged), for several seeds in one program; then the buffer bytes for other task counts.

    python -m benchmarks.memory [--tiny | --full] [--out DIR] [--threads N]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks import harness
from mpcpearl_jax.cli.stopping import stops_with

SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(preset="smoke", seeds=(1,), tasks=(10, 120), iterate=False),
    "default": dict(preset="paper", seeds=(1, 2), tasks=(30, 120, 480), iterate=True),
    "full": dict(preset="paper", seeds=(1, 2, 4, 8), tasks=(30, 120, 480, 1920), iterate=True),
}
MB = 2**20


def proc_status_mb() -> dict[str, float]:
    """VmRSS (current) and VmHWM (peak) resident memory of this process in MiB."""
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            key = line.split(":")[0]
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(line.split()[1]) / 1024  # kB
    return out


def tree_mb(tree) -> float:
    import jax

    return sum(x.nbytes for x in jax.tree_util.tree_leaves(tree)) / MB


def experiment(preset_name: str, seeds: int):
    """The preset with `seeds` seeds, MPC off and a 2-step update phase (same buffer sizes)."""
    import dataclasses

    from mpcpearl_jax.config import preset

    cfg = preset(preset_name)
    train = dataclasses.replace(cfg.train, eps=0.0, updates_per_iteration=2)
    return cfg.replace(seeds=seeds, train=train)


# ------------------------------------------------------------------------- child runs
def child_run(preset_name: str, seeds: int, iterate: bool) -> dict[str, Any]:
    """Build a trainer, init its state (and run one iteration); report bytes and RSS."""
    import jax

    from mpcpearl_jax.training.trainer import Trainer

    jax.block_until_ready(jax.numpy.zeros(1))
    cfg = experiment(preset_name, seeds)
    trainer = Trainer(cfg)
    base = proc_status_mb()
    state = trainer.init_state()
    jax.block_until_ready(state)
    after_init = proc_status_mb()
    out: dict[str, Any] = {
        "seeds": seeds,
        "num_tasks": trainer.num_train,
        "rl_capacity_per_task": cfg.train.rl_capacity,
        "enc_capacity_per_task": trainer.enc_capacity,
        "rl_buffers_mb": tree_mb(state.rl),
        "enc_buffers_mb": tree_mb(state.enc),
        "learner_mb": tree_mb(state.learner),
        "state_mb": tree_mb(state),
        "rss_baseline_mb": base["VmRSS"],
        "rss_after_init_mb": after_init["VmRSS"],
        "peak_after_init_mb": after_init["VmHWM"],
    }
    if iterate:
        t0 = time.perf_counter()
        state, _ = trainer.iteration(state)
        jax.block_until_ready(state)
        out["iteration_s_incl_compile"] = time.perf_counter() - t0
        end = proc_status_mb()
        out["rss_after_iteration_mb"] = end["VmRSS"]
        out["peak_rss_mb"] = end["VmHWM"]
    else:
        out["peak_rss_mb"] = after_init["VmHWM"]
    out["peak_over_baseline_mb"] = out["peak_rss_mb"] - base["VmRSS"]
    return out


def child_buffers(preset_name: str, tasks: int) -> dict[str, Any]:
    """Bytes and RSS growth of one seed's RL + encoder buffers for `tasks` tasks."""
    import jax

    from mpcpearl_jax import make_env
    from mpcpearl_jax.pearl import buffers

    cfg = experiment(preset_name, 1)
    env = make_env(cfg.env)
    obs_dim, act_dim = 25, env.action_dim
    enc_cap = cfg.train.prior_episodes * env.config.horizon
    jax.block_until_ready(jax.numpy.zeros(1))
    base = proc_status_mb()
    rl = buffers.init_buffer(tasks, cfg.train.rl_capacity, obs_dim, act_dim)
    enc = buffers.init_buffer(tasks, enc_cap, obs_dim, act_dim)
    jax.block_until_ready((rl, enc))
    end = proc_status_mb()
    return {
        "num_tasks": tasks,
        "buffers_mb": tree_mb(rl) + tree_mb(enc),
        "rss_growth_mb": end["VmRSS"] - base["VmRSS"],
        "peak_growth_mb": end["VmHWM"] - base["VmRSS"],
    }


def in_child(args: list[str], threads: int) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "benchmarks.memory", "--child", *args, "--threads", str(threads)]
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=root)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


@stops_with("interrupted; the memory record is not written")
def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument("--child", nargs=4, help=argparse.SUPPRESS)  # KIND PRESET N ITERATE
    args = p.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    if args.child:
        kind, preset_name, n, iterate = args.child
        if kind == "run":
            row = child_run(preset_name, int(n), iterate == "1")
        else:
            row = child_buffers(preset_name, int(n))
        print(json.dumps(row), flush=True)
        return row

    size = harness.size_of(args)
    sz = SIZES[size]
    t0 = time.perf_counter()
    it = str(int(sz["iterate"]))
    runs = [in_child(["run", sz["preset"], str(s), it], threads["threads"]) for s in sz["seeds"]]
    bufs = [
        in_child(["buffers", sz["preset"], str(n), "0"], threads["threads"]) for n in sz["tasks"]
    ]
    harness.print_table(
        runs,
        [
            "seeds",
            "num_tasks",
            "rl_buffers_mb",
            "enc_buffers_mb",
            "learner_mb",
            "state_mb",
            "rss_baseline_mb",
            "rss_after_init_mb",
            "peak_rss_mb",
            "peak_over_baseline_mb",
        ],
        f"Training state of the '{sz['preset']}' preset (MiB; RSS from /proc/self/status)",
    )
    harness.print_table(
        bufs,
        ["num_tasks", "buffers_mb", "rss_growth_mb", "peak_growth_mb"],
        "RL + encoder buffers of one seed vs. number of tasks (MiB)",
    )
    results = {
        "runs": runs,
        "buffers_by_tasks": bufs,
        "wall_s": time.perf_counter() - t0,
        "method": "array nbytes + VmRSS/VmHWM of a fresh child process per row",
    }
    config = {
        "size": size,
        **sz,
        "threads": threads,
        "note": "eps = 0 and 2 updates per iteration; buffer sizes as in the preset",
    }
    harness.write_record("memory", config, results, args.out)
    return results


if __name__ == "__main__":
    main()
