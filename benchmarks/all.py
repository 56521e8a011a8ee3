"""Run every benchmark script, each in its own process, and collect their JSON records.

    python -m benchmarks.all --record   # about 13 minutes on a 2-core CPU: the committed records
    python -m benchmarks.all            # the same into benchmarks/results/scratch/ (git-ignored)
    python -m benchmarks.all --full     # the paper's sizes (hours)
    python -m benchmarks.all --tiny     # seconds per script (smoke test; never with --record)
    options: --record (write benchmarks/results/) or --out DIR (default
    benchmarks/results/scratch/), --threads N, --only NAME [NAME ...]

Each script gets the same size flag, `--out` and `--threads`. With `--full`, the PEARL step is
also measured with 1 thread (into OUT/threads1/), as in the authors' same-CPU anchor. A script
that fails is reported and the others still run; the exit status is non-zero if any failed.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from benchmarks import harness
from mpcpearl_jax.cli.stopping import stops_with

# Run order: cheap and independent first. mpc_latency.py belongs to the MPC module.
SCRIPTS = (
    "env_throughput",
    "collection",
    "pearl_step",
    "learner_sizes",
    "policy_latency",
    "mpc_latency",
    "mpc_bridge",
    "memory",
    "iteration",
    "pipeline",
    "grbal_planner",
)


# Scripts with their own command line (no --tiny/--full/--threads): arguments per size.
OWN_ARGS = {
    "mpc_latency": {
        "tiny": ["--tasks", "1"],
        "default": ["--tasks", "8"],
        "full": ["--tasks", "24"],
    }
}


def run_script(name: str, size: str, out: Path, threads: int | None) -> dict:
    """Run `python -m benchmarks.NAME` at `size`; returns {name, rc, wall_s, cmd}."""
    cmd = [sys.executable, "-m", f"benchmarks.{name}", "--out", str(out)]
    if name in OWN_ARGS:
        cmd += OWN_ARGS[name][size]
    else:
        cmd += [] if size == "default" else [f"--{size}"]
        if threads:
            cmd += ["--threads", str(threads)]
    print(f"\n=== {' '.join(cmd[1:])}", flush=True)
    t0 = time.perf_counter()
    rc = subprocess.run(cmd, check=False, cwd=Path(__file__).resolve().parents[1]).returncode
    wall = time.perf_counter() - t0
    print(f"=== {name}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} in {wall:.0f} s", flush=True)
    return {"name": name, "rc": rc, "wall_s": wall, "cmd": cmd[1:]}


@stops_with("interrupted; the benchmarks run so far wrote their records, all.json is not written")
def main(argv: list[str] | None = None) -> int:
    p = harness.common_parser(__doc__.split("\n\n")[0])  # --out or --record checked up front
    p.add_argument("--only", nargs="+", choices=SCRIPTS, default=None)
    args = p.parse_args(argv)
    harness.check_platform_or_fail()  # once here, not once per script
    size = "tiny" if args.tiny else "full" if args.full else "default"
    out = Path(args.out)
    here = Path(__file__).parent
    runs = []
    t0 = time.perf_counter()
    for name in args.only or SCRIPTS:
        if not (here / f"{name}.py").is_file():
            print(f"\n=== {name}: skipped (benchmarks/{name}.py is not present)", flush=True)
            runs.append({"name": name, "rc": None, "wall_s": 0.0})
            continue
        runs.append(run_script(name, size, out, args.threads))
        if name == "pearl_step" and args.full and args.threads != 1:
            runs.append(run_script(name, size, out / "threads1", 1))
    total = time.perf_counter() - t0
    harness.print_table(runs, ["name", "rc", "wall_s"], f"benchmarks.all ({total:.0f} s)")
    out.mkdir(parents=True, exist_ok=True)
    summary = {
        "runs": runs,
        "total_s": total,
        "machine": harness.machine_info(),
        "size": size,
    }
    (out / "all.json").write_text(json.dumps(summary, indent=2))
    return 1 if any(r["rc"] not in (0, None) for r in runs) else 0


if __name__ == "__main__":
    sys.exit(main())
