"""The robustness records: runs (and GP-MPC) on the 192 validation tasks with the crowd re-timed.

    python -m lab.robustness results/restaurant/mpc-pearl-eps0.2 [RUN ...]
    python -m lab.robustness --all               # every committed restaurant policy
    python -m lab.robustness --gp-mpc            # the GP-MPC baseline
    python -m lab.robustness RUN --perturb delay=9 --perturb speed=0.85

For every run and every perturbation (default: none and the robustness table's delay 3, 6, 12,
speed 0.7, 1.3; `envs.perturb`, docs/method.md §8a) this is

    mpcpearl_jax.evaluate(RUN, split="val", task_seeds="1-8", perturb=P, out=...)

(`python -m experiments.evaluate RUN --split val --task-seeds 1-8 --perturb P --figures none`;
GP-MPC: `controller="gp-mpc", env="restaurant"`, records under results/gp_mpc/perturbed/), all
in one process so that each run's evaluator is compiled once. A record that exists is kept
(`--overwrite` redoes it). `python -m lab.table` turns the records into the table.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mpcpearl_jax.envs.perturb import parse_perturbation

ROOT = Path(__file__).resolve().parents[1]
TABLE_PERTURBATIONS = ("none", "delay=3", "delay=6", "delay=12", "speed=0.7", "speed=1.3")
GP_MPC_OUT = Path("results") / "gp_mpc" / "perturbed"
# written by `experiments.evaluate --controller gp-mpc --env restaurant --split val --task-seeds
# 1-8` for the main table
GP_MPC_UNPERTURBED = Path("results") / "gp_mpc" / "restaurant_val_seeds1-8.json"
TASK_SEEDS = "1-8"


def suffix(text: str) -> str:
    """The folder suffix experiments.evaluate gives a perturbation ('' for none)."""
    return parse_perturbation(text).folder_suffix


def committed_runs(results: Path) -> list[Path]:
    """Every committed restaurant run with a policy (not GrBAL's model), relative to the working
    directory where it lies below it (the records name the run: no machine paths in them)."""
    runs = sorted(p.parent for p in (results / "restaurant").rglob("policy.msgpack"))
    runs = [r for r in runs if (r / "config.json").is_file() and not _is_grbal(r)]
    here = Path.cwd().resolve()
    return [r.resolve().relative_to(here) if r.resolve().is_relative_to(here) else r for r in runs]


def _is_grbal(run: Path) -> bool:
    """A GrBAL run: a dynamics model planned with MPPI, evaluated by experiments.grbal."""
    from mpcpearl_jax import algorithms

    return algorithms.of_run(run) is algorithms.GRBAL


def record_path(run: Path | None, text: str) -> Path:
    if run is None:
        return GP_MPC_OUT / f"val{suffix(text)}-seeds{TASK_SEEDS}" / "results.json"
    return run / "eval" / f"policy-val{suffix(text)}-seeds{TASK_SEEDS}" / "results.json"


def evaluate(run: Path | None, perturb: str, out: Path, overwrite: bool) -> bool:
    """The record of `run` (None: GP-MPC on the restaurant) with the crowd perturbed by
    `perturb` (`mpcpearl_jax.evaluate`) written into `out`; whether it was (a failure is one
    line on stderr)."""
    import mpcpearl_jax
    from mpcpearl_jax.errors import CheckpointError

    where = {"controller": "gp-mpc", "env": "restaurant"} if run is None else {}
    try:
        ev = mpcpearl_jax.evaluate(
            run,
            **where,
            split="val",
            task_seeds=TASK_SEEDS,
            figures="none",
            perturb=perturb,
            out=out,
            overwrite=overwrite,
        )
    except (ValueError, OSError, CheckpointError) as e:
        line = (str(e).strip().splitlines() or [type(e).__name__])[0]
        print(f"error: {run or 'GP-MPC'} {perturb}: {line}", file=sys.stderr, flush=True)
        return False
    pooled = ev.record["pooled"]
    print(
        f"[robustness] {ev.setup.label} {perturb}: SR {pooled['SR']['mean']:.2f} "
        f"+- {pooled['SR']['se']:.2f}, wrote {out / 'results.json'}",
        flush=True,
    )
    return True


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", type=Path, nargs="*", help="run directories")
    p.add_argument("--all", action="store_true", help="every committed restaurant policy")
    p.add_argument("--gp-mpc", action="store_true", help="the GP-MPC baseline too")
    p.add_argument(
        "--perturb",
        action="append",
        default=None,
        help="a perturbation (repeatable; default: none and the table's five)",
    )
    p.add_argument("--overwrite", action="store_true", help="redo existing records")
    args = p.parse_args(argv)
    perturbations = args.perturb or list(TABLE_PERTURBATIONS)
    try:
        for text in perturbations:
            parse_perturbation(text)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    runs: list[Path | None] = list(args.runs)
    if args.all:
        runs += [r for r in committed_runs(ROOT / "results") if r not in runs]
    if args.gp_mpc:
        runs.append(None)
    if not runs:
        print("error: give run directories, --all or --gp-mpc", file=sys.stderr)
        return 2
    for run in runs:
        if run is not None and not (run / "config.json").is_file():
            print(f"error: {run}: not a run directory (no config.json)", file=sys.stderr)
            return 2

    failed = []
    for run in runs:
        for text in perturbations:
            if run is None and parse_perturbation(text).is_identity:
                # the table reads the main table's unperturbed GP-MPC record
                print(f"[robustness] kept {GP_MPC_UNPERTURBED}", flush=True)
                continue
            out = record_path(run, text)
            if out.is_file() and not args.overwrite:
                print(f"[robustness] kept {out}", flush=True)
                continue
            name = "GP-MPC" if run is None else str(run)
            t0 = time.perf_counter()
            ok = evaluate(run, text, out.parent, args.overwrite)
            print(
                f"[robustness] {name} {text}: {'done' if ok else 'failed'}, "
                f"{time.perf_counter() - t0:.0f} s"
            )
            if not ok:
                failed.append(f"{name} {text}")
    if failed:
        print(f"error: {len(failed)} evaluation(s) failed: {failed}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
