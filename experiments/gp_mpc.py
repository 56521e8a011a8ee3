"""GP-MPC baseline (the paper's "GP-MPC" column): the risk-aware MPC acting at every step.

    python -m experiments.gp_mpc --env restaurant --split test [--set v_max=5.0 --set alpha=0.95]
    python -m experiments.gp_mpc --scenarios path/to/MPC-PEARL --split test   # the paper's tasks
    python -m experiments.gp_mpc --scenarios path/to/MPC-PEARL --split train --tasks 0:30
    python -m experiments.gp_mpc --scenarios path/to/MPC-PEARL --preset default   # the teacher

The MPC settings are the `paper` preset's (the SQP to convergence, method §7) unless --preset
names another preset, whose MPC is taken (e.g. `default`: 2 QPs per solve and the unsafe-plan
recovery, the expert the learned presets train with); --set changes them further.

Prints the method §8 metrics next to the paper's numbers, the MPC status counts and solve times, and
writes a JSON record and a trajectory figure (one task) under --out. The record is named
`ENV_SPLIT[_tasksA-B][_preset-NAME][_seedN][_sample-seedN][_set-...].json`: the task range when
not the whole split (--tasks, --max-tasks), then each of --preset (other than paper), --seed,
--sample-seed (other than 0) and --set, so runs with other settings keep their own records; a
record of the same name made with other settings (another --scenarios, --data or --env module) is
never replaced without --overwrite, checked before the rollout. A stop signal (Ctrl-C,
SIGTERM, SIGHUP) ends it with one line and exit code 128 + the signal, nothing written; the
rollout of all tasks is one program, so the stop takes effect when it ends (--tasks makes it
shorter).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
import time
from pathlib import Path

import jax
import numpy as np

from experiments.common import add_task_source_options, env_family, one_line_errors, stops_with
from mpcpearl_jax.cli.output import broken_line, guarded_stdout
from mpcpearl_jax.cli.platform import check_platform
from mpcpearl_jax.config import ExperimentConfig, apply_overrides, preset, task_source
from mpcpearl_jax.envs import make_env, mpc_defaults, tasks_for
from mpcpearl_jax.evaluation import metrics
from mpcpearl_jax.evaluation.report import PAPER, metrics_table
from mpcpearl_jax.mpc import MPCConfig, make_gp_mpc_rollout, make_mpc_bridge
from mpcpearl_jax.validate import unwritable_folder


def select_tasks(tasks, span: str | None, max_tasks: int | None, plot_task: int | None):
    """The tasks of --tasks START:STOP (the split's tasks START to STOP - 1; either may be left
    out), then of --max-tasks (the first N of them), and the index among them of --plot-task (a
    task of the split; default the first selected) -> (tasks, first task's index, plot index);
    ValueError naming the flag."""
    n = tasks.num_tasks
    lo, hi = 0, n
    if span is not None:
        start, sep, stop = span.partition(":")
        try:
            lo = int(start) if start.strip() else 0
            hi = int(stop) if stop.strip() else n
        except ValueError:
            sep = ""
        if not sep or lo < 0 or hi <= lo:
            raise ValueError(f"--tasks {span}: not START:STOP with 0 <= START < STOP (e.g. 0:30)")
        if lo >= n or hi > n:  # refused, not cut silently to the split's tasks
            raise ValueError(
                f"--tasks {span}: the {n} tasks of the split are 0 to {n - 1} (STOP at most {n})"
            )
    if max_tasks is not None:
        if max_tasks < 1:
            raise ValueError(f"--max-tasks must be positive, got {max_tasks}")
        hi = min(hi, lo + max_tasks)
    hi = min(hi, n)
    plot = lo if plot_task is None else plot_task
    if not lo <= plot < hi:
        raise ValueError(f"--plot-task {plot_task}: not among the tasks run ({lo} to {hi - 1})")
    return jax.tree_util.tree_map(lambda a: a[lo:hi], tasks), lo, plot - lo


def mpc_settings(env: str, preset_name: str, overrides: list[str]) -> MPCConfig:
    """The MPC of `preset_name` (--preset), under the family's MPC defaults, then the --set
    `overrides`; ConfigError naming the preset or the field."""
    base = preset(preset_name).mpc.replace(**mpc_defaults(env))
    return apply_overrides(base, overrides)


@stops_with("interrupted before GP-MPC finished; nothing was written")
def main(argv: list[str] | None = None) -> int:
    """The command. A standard output that breaks (`| head`, a full disk) loses nothing: the
    record and the figure are written before anything is printed, then one line on stderr and
    exit code 2."""
    with guarded_stdout() as stdout:
        code = _main(argv)
    if stdout.broken is not None:
        what = "the record and the figure are written" if code == 0 else "see above"
        print(broken_line(stdout.broken, what), file=sys.stderr, flush=True)
        return code or 2
    return code


def _main(argv: list[str] | None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.gp_mpc", description=__doc__)
    ap.add_argument("--env", default="restaurant")
    ap.add_argument("--split", default="test")
    ap.add_argument("--seed", type=int, default=0, help="task-set seed")
    ap.add_argument("--sample-seed", type=int, default=0, help="seed of the GP samples")
    ap.add_argument(
        "--preset",
        default="paper",
        metavar="NAME",
        help="take the MPC settings of this preset (default: paper, the SQP to convergence; "
        "default: the expert the learned presets train with)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override an MPCConfig field (repeatable; values read by the field's type)",
    )
    ap.add_argument("--out", type=Path, default=Path("runs") / "gp_mpc")
    ap.add_argument(
        "--plot-task",
        type=int,
        metavar="I",
        help="the split's task the trajectory figure shows (default: the first one run)",
    )
    ap.add_argument(
        "--max-tasks", type=int, help="only the first N tasks of the split (of --tasks)"
    )
    ap.add_argument(
        "--tasks",
        metavar="START:STOP",
        help="only the split's tasks START to STOP - 1, e.g. --tasks 0:30 (default: all)",
    )
    ap.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a record of the same name made with other settings",
    )
    add_task_source_options(ap)
    args = ap.parse_args(argv)

    with one_line_errors(interrupted=None) as failed:
        check_platform()  # JAX_PLATFORMS naming a platform this machine lacks: one line
        args.env = env_family(args.env)  # MODULE:NAME registers NAME
        env = make_env(args.env)
        cfg = mpc_settings(args.env, args.preset, args.set)
        source = task_source(args.env, args.scenarios, data=args.data)
        tasks = tasks_for(ExperimentConfig(env=args.env, **source), args.split, seed=args.seed)
        n_split = tasks.num_tasks
        tasks, first, plot = select_tasks(tasks, args.tasks, args.max_tasks, args.plot_task)
        last = first + tasks.num_tasks - 1
        path = args.out / record_name(args, first, last + 1, n_split)
        settings = record_settings(args, source, first, last + 1, cfg)
        probe_out(args.out)  # before the rollout, not after it
        check_replace(path, settings, args.overwrite)
    if failed.code is not None:
        return failed.code
    bridge = make_mpc_bridge(env, cfg)
    t0 = time.perf_counter()
    traj = jax.jit(make_gp_mpc_rollout(env, bridge))(jax.random.PRNGKey(args.sample_seed), tasks)
    traj = jax.tree_util.tree_map(np.asarray, jax.block_until_ready(traj))
    wall = time.perf_counter() - t0
    bridge.close()
    m = metrics.compute(
        traj["position"], traj["collision"], traj["in_goal"], tasks.goal, env.config.robot_radius
    )
    stats = bridge.stats()
    paper = PAPER.get(args.env, {}).get("GP-MPC", {})
    solve_ms = 1e3 * np.asarray(stats["solve_s"])  # per row on the host; none on the device
    med = float(np.median(solve_ms)) if solve_ms.size else None
    p95 = float(np.percentile(solve_ms, 95)) if solve_ms.size else None
    record = {
        **settings,
        "metrics": m,
        "paper": paper,
        "status": stats["status"],
        "reasons": stats["reasons"],
        "sqp_stops": stats["sqp_stops"],
        "starts": stats["starts"],
        "solve_ms_median": med,
        "solve_ms_p95": p95,
        "wall_s": wall,
        "per_task": {k: traj[k].sum(axis=1).tolist() for k in ("collision", "in_goal")},
    }
    with one_line_errors(interrupted=None) as failed:  # written before anything is printed
        path.write_text(json.dumps(record, indent=2))
        png = _plot(args, env, tasks, traj, plot, first + plot)
    if failed.code is not None:
        return failed.code
    print(
        f"GP-MPC on {args.env}/{args.split}: {tasks.num_tasks} tasks ({first} to {last}), "
        f"{wall:.1f} s"
    )
    print(metrics_table([("this run", m), ("paper GP-MPC", paper)]))
    print(f"status: {stats['status']}  reasons: {stats['reasons']}")
    if stats["sqp_stops"]:  # why each row's SQP ended (capped: the cap's best iterate was used)
        print(f"SQP ended: {stats['sqp_stops']}  plans from starts: {stats['starts']}")
    if solve_ms.size:
        print(f"solve ms: median {med:.2f}, p95 {p95:.2f}")
    print(f"wrote {path}")
    print(f"wrote {png}")
    return 0


def record_settings(args, source: dict, start: int, stop: int, cfg: MPCConfig) -> dict:
    """The record's fields that say what was run (its first fields, in this order)."""
    return {
        "env": args.env,
        "split": args.split,
        "tasks": [start, stop],  # the split's tasks start to stop - 1
        "data": str(args.data) if args.data else None,
        "scenarios": source.get("task_options"),
        "seed": None if args.scenarios is not None else args.seed,
        "sample_seed": args.sample_seed,
        "preset": args.preset,
        "mpc": cfg.to_dict(),
    }


def record_name(args, start: int, stop: int, n_split: int) -> str:
    """The record's file name: ENV_SPLIT, the task range when not the whole split, then each
    setting that is not the default (module doc)."""
    name = f"{args.env}_{args.split}"
    if args.tasks or (start, stop) != (0, n_split):
        name += f"_tasks{start}-{stop}"
    if args.preset != "paper":
        name += f"_preset-{args.preset}"
    if args.scenarios is None and args.seed != 0:
        name += f"_seed{args.seed}"
    if args.sample_seed != 0:
        name += f"_sample-seed{args.sample_seed}"
    if args.set:
        text = "+".join(re.sub(r"[^A-Za-z0-9._=-]", "-", s.strip()) for s in args.set)
        if len(text) > 80:  # a name the file system takes; the record holds every field
            text = hashlib.sha1("\n".join(args.set).encode()).hexdigest()[:12]
        name += f"_set-{text}"
    return re.sub(r"[^A-Za-z0-9._=+-]", "-", name) + ".json"


def check_replace(path: Path, settings: dict, overwrite: bool) -> None:
    """FileExistsError in one line when `path` holds a record made with other `settings` (or
    something that is not a record of this command), unless `overwrite`."""
    if overwrite or not path.exists():
        return
    try:
        old = json.loads(path.read_text())
        differ = [k for k in settings if old.get(k) != json.loads(json.dumps(settings[k]))]
    except (OSError, ValueError, AttributeError):
        differ = ["(not a record of this command)"]
    if differ:
        raise FileExistsError(
            f"{path}: holds a record made with other settings ({', '.join(differ)}); "
            "choose another --out, or add --overwrite to replace it"
        )


def probe_out(out: Path) -> None:
    """Create --out and prove it writable (a probe file written and removed); OSError in one
    line naming it otherwise."""
    why = unwritable_folder(out)
    if why is not None:
        raise OSError(f"--out {out}: not writable ({why}); choose another --out")


def _plot(args, env, tasks, traj, i: int, task: int) -> Path:
    """The trajectory of tasks[i], the split's task `task`: its figure's path."""
    from mpcpearl_jax.envs import save_trajectory

    params = jax.tree_util.tree_map(lambda a: a[i], tasks)
    png = save_trajectory(
        args.env,
        args.out / f"{args.env}_{args.split}_task{task}.png",
        params,
        {"GP-MPC": (traj["position"][i], traj["collision"][i])},
        env.config,
        title=f"GP-MPC, {args.env} {args.split} task {task}",
    )
    return png


if __name__ == "__main__":
    sys.exit(main())
