"""Why the host SQP stays in runs of fallbacks: GP-MPC on chosen scenarios, and at every step the
same problem also solved from the other starts (cold, standing still), which the controller does
not use, so the closed loop is the setting's own.

Per step it records the row's status and reason, the age of its warm start (steps since the last
safe plan: a fallback keeps the previous plan shifted, and the next solve starts from it again),
the first-stage violation of the warm start itself, and whether the SQP from each other start
would have given a safe plan. A run of fallbacks that a cold start or a stop would have ended is a
warm-start trap; one that no start ends is a problem with no safe first move the SQP can find.

    python -m lab.diagnostics.fallback_runs --scenarios DIR --tasks 150 36 91 [--set sqp_iters=2]

Record: results/mpc/convergence/fallback-runs.json (and a summary printed). A record of other
--tasks or MPC settings (--set) at --out is never replaced without --overwrite, checked before
the rollout.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from lab.convergence import OUT, ROOT, _scenario_tasks
from mpcpearl_jax.cli.stopping import stops_with


@stops_with("stopped: the record is written once every task has run, before the table is printed")
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lab.diagnostics.fallback_runs")
    ap.add_argument(
        "--scenarios", type=Path, default=ROOT.parent / "shared" / "data" / "mpc-pearl-scenarios"
    )
    ap.add_argument("--tasks", type=int, nargs="+", required=True, help="indices 0-204 (180+ test)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--out", default=str(OUT / "fallback-runs.json"), help="the record (NAME.json)")
    ap.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a record at --out made with other --tasks or --set",
    )
    args = ap.parse_args(argv)

    from lab import harness
    from mpcpearl_jax.validate import unwritable_folder

    # the record's place is checked before the rollout: it is written once every task has run
    folder = args.out.endswith(("/", os.sep))  # "DIR/" names a folder, there or not
    args.out = Path(args.out)
    if folder or args.out.is_dir():
        harness.fail(f"--out {args.out}: a folder; give the record's file name (NAME.json)")
    why = unwritable_folder(args.out.parent)
    if why is not None:
        harness.fail(f"--out {args.out}: not writable ({why}); choose another --out")

    import jax

    from mpcpearl_jax.config import apply_overrides
    from mpcpearl_jax.envs import make_env, mpc_defaults
    from mpcpearl_jax.errors import ConfigError, DataFormatError
    from mpcpearl_jax.mpc import HostSolver, MPCBridge, MPCConfig, SQPSolver, make_gp_mpc_rollout
    from mpcpearl_jax.mpc.problem import solver_params, starts
    from mpcpearl_jax.mpc.rows import FALLBACK_PLAN, FALLBACK_POLICY

    env = make_env("restaurant")
    try:
        cfg = apply_overrides(MPCConfig(**mpc_defaults("restaurant")), args.set)
    except ConfigError as e:
        harness.fail(str(e))
    why = _other_record(args.out, args.tasks, cfg.to_dict(), args.overwrite)
    if why is not None:
        harness.fail(why)
    try:
        tasks = _scenario_tasks(env, args.scenarios)
    except (OSError, DataFormatError) as e:
        harness.fail(f"--scenarios: {e}")
    n = len(tasks.start)
    outside = [str(t) for t in args.tasks if not 0 <= t < n]
    if outside:
        harness.fail(f"--tasks {' '.join(outside)}: the {n} scenarios are indices 0-{n - 1}")
    tasks = jax.tree_util.tree_map(lambda a: a[np.asarray(args.tasks)], tasks)
    log: list[list[dict]] = []

    class Probe(HostSolver):
        def solve_rows(self, probs, inits, num_static):
            results = super().solve_rows(probs, inits, num_static)
            params = solver_params(self.cfg, self.nav, num_static)
            solver = SQPSolver(params, self.qp)
            step = []
            for prob, u0, res in zip(probs, inits, results, strict=True):
                others = {}
                for name, u in starts(params, prob, u0)[1:]:
                    others[name] = solver._sqp(prob, u).reason == "solved"
                warm_viol = None
                if u0 is not None:
                    from mpcpearl_jax.mpc import model

                    xs = model.rollout(prob.x0, u0, params.dt, params.wheelbase)
                    warm_viol = solver._first_violation(prob, xs)
                step.append(
                    dict(
                        reason=res.reason,
                        start=res.start,
                        warm=u0 is not None,
                        warm_violation=warm_viol,
                        others_safe=others,
                    )
                )
            log.append(step)
            return results

    bridge = MPCBridge(env, cfg, host=Probe(env.config, cfg))
    traj = jax.jit(make_gp_mpc_rollout(env, bridge))(jax.random.PRNGKey(0), tasks)
    traj = jax.tree_util.tree_map(np.asarray, jax.block_until_ready(traj))
    status = traj["status"]
    out = {"mpc": cfg.to_dict(), "tasks": args.tasks, "per_task": []}
    for j, task in enumerate(args.tasks):
        fb = np.isin(status[j], (FALLBACK_PLAN, FALLBACK_POLICY))
        steps = [log[t][j] for t in range(len(log))]
        in_run = [s for s, f in zip(steps, fb, strict=False) if f]
        cold_ok = sum(bool(s["others_safe"].get("cold")) for s in in_run)
        stop_ok = sum(bool(s["others_safe"].get("stop")) for s in in_run)
        any_ok = sum(any(s["others_safe"].values()) for s in in_run)
        first_collision = (
            int(np.argmax(traj["collision"][j])) if traj["collision"][j].any() else None
        )
        rec = dict(
            task=task,
            fallbacks=int(fb.sum()),
            first_collision=first_collision,
            fallback_steps_where_cold_is_safe=cold_ok,
            fallback_steps_where_stop_is_safe=stop_ok,
            fallback_steps_where_some_start_is_safe=any_ok,
            status=status[j].tolist(),
            steps=steps,
        )
        out["per_task"].append(rec)
    out["summary"] = _summary(out["per_task"])
    # the record before the lines: a failing or closed standard output loses none of the work
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, separators=(",", ":"), default=float))
    for rec in out["per_task"]:
        print(
            f"task {rec['task']}: {rec['fallbacks']} fallbacks, first collision at step "
            f"{rec['first_collision']}; on those steps a cold start is safe on "
            f"{rec['fallback_steps_where_cold_is_safe']}, standing still on "
            f"{rec['fallback_steps_where_stop_is_safe']}, some start on "
            f"{rec['fallback_steps_where_some_start_is_safe']}",
            flush=True,
        )
    print(json.dumps(out["summary"], indent=1))
    print(f"wrote {args.out}")
    return 0


def _other_record(out: Path, tasks: list[int], mpc: dict, overwrite: bool) -> str | None:
    """The one-line refusal where `out` holds a record made with other `tasks` or `mpc`
    settings (or something that is not this diagnostic's record), unless `overwrite`; None
    where it may be written."""
    if overwrite or not out.exists():
        return None
    try:
        old = json.loads(out.read_text())
        mpc = json.loads(json.dumps(mpc, default=float))  # as the record holds it
        differ = [k for k, v in (("tasks", tasks), ("mpc", mpc)) if old.get(k) != v]
    except (OSError, ValueError, AttributeError):
        differ = ["(not a record of this diagnostic)"]
    if not differ:
        return None
    return (
        f"--out {out}: holds a record made with other settings ({', '.join(differ)}); choose "
        "another --out, or add --overwrite to replace it"
    )


def _summary(per_task: list[dict], window: int = 3) -> dict:
    """Over the tasks: episodes with a collision; fallback steps before and after the first
    collision; collisions with a fallback in the `window` steps before them, and among those the
    ones where a cold start or standing still would have given a safe plan on that step."""
    fallback = (2, 3)  # mpc.rows FALLBACK_PLAN, FALLBACK_POLICY
    s = dict(
        tasks=len(per_task),
        collided=0,
        fallback_steps_before=0,
        fallback_steps_after=0,
        collisions_after_a_fallback=0,
        collisions_after_an_avoidable_fallback=0,
    )
    for r in per_task:
        fc = r["first_collision"]
        steps = [i for i, st in enumerate(r["status"]) if st in fallback]
        if fc is None:
            s["fallback_steps_before"] += len(steps)
            continue
        s["collided"] += 1
        s["fallback_steps_before"] += sum(i < fc for i in steps)
        s["fallback_steps_after"] += sum(i >= fc for i in steps)
        near = [i for i in steps if fc - window <= i < fc]
        if near:
            s["collisions_after_a_fallback"] += 1
            if any(any(r["steps"][i]["others_safe"].values()) for i in near):
                s["collisions_after_an_avoidable_fallback"] += 1
    return s


if __name__ == "__main__":
    sys.exit(main())
