"""GP-MPC baseline (the paper's "GP-MPC" column): the risk-aware MPC acting at every step.

    python -m experiments.gp_mpc --env restaurant --split test [--set v_max=5.0 --set alpha=0.95]
    python -m experiments.gp_mpc --scenarios path/to/MPC-PEARL --split test   # the paper's tasks
    python -m experiments.gp_mpc --scenarios path/to/MPC-PEARL --split train --tasks 0-29
    python -m experiments.gp_mpc --scenarios path/to/MPC-PEARL --preset default   # the teacher

The MPC settings are the `paper` preset's (the SQP to convergence, method §7) unless --preset
names another preset, whose MPC is taken (e.g. `default`: 2 QPs per solve and the unsafe-plan
recovery, the expert the learned presets train with); --set changes them further.

The rollout is `mpcpearl_jax.evaluate(controller="gp-mpc", ...)`, the path of `python -m
experiments.evaluate --controller gp-mpc`; --tasks takes its task syntax (0,3,5; 0-3 inclusive;
0:30, 30 excluded; a mix).

Prints the method §8 metrics next to the paper's numbers, the MPC status counts and solve times, and
writes a JSON record and a trajectory figure (one task) under --out. The record is named
`ENV_SPLIT[_tasksA-B][_preset-NAME][_seedN][_sample-seedN][_set-...].json`: the task range when
not the whole split (--tasks, --max-tasks; tasks A to B - 1, or _tasksI+J+K when they are not
consecutive), then each of --preset (other than paper), --seed,
--sample-seed (other than 0) and --set, so runs with other settings keep their own records; a
record of the same name made with other settings (another --scenarios, --data or --env module) is
never replaced without --overwrite, checked before the rollout. The figure is named after its
record, `<record's name>_taskI.png` (task I of the split), so it is replaced only with it. A
stop signal (Ctrl-C, SIGTERM, SIGHUP) ends it with one line and exit code 128 + the signal,
nothing written; the rollout of all tasks is one program, so the stop takes effect when it ends
(--tasks makes it shorter).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

from experiments.common import add_task_source_options, one_line_errors, stops_with
from mpcpearl_jax.api.evaluate import Plan, prepare
from mpcpearl_jax.cli.evaluate import flags
from mpcpearl_jax.cli.output import broken_line, guarded_stdout
from mpcpearl_jax.cli.platform import check_platform
from mpcpearl_jax.evaluation import metrics
from mpcpearl_jax.evaluation.plan import mpc_settings as mpc_fields
from mpcpearl_jax.evaluation.report import PAPER, metrics_table
from mpcpearl_jax.mpc import MPCConfig
from mpcpearl_jax.validate import unwritable_folder

# this command's names of `mpcpearl_jax.evaluate`'s arguments where they differ
FLAGS = {"task_seed": "--seed", "eval_seed": "--sample-seed", "mpc": "--set"}


def mpc_settings(env: str, preset_name: str, overrides: list[str]) -> MPCConfig:
    """The MPC of `preset_name` (--preset), under the family's MPC defaults, then the --set
    `overrides` (`mpcpearl_jax.evaluation.plan.mpc_settings`); ValueError naming the preset or
    the field."""
    return MPCConfig(**mpc_fields(env, None, preset_name, overrides))


def plan(args: argparse.Namespace) -> Plan:
    """The GP-MPC evaluation of the command line `args` (`mpcpearl_jax.evaluate`'s plan, nothing
    written by it): --tasks, then the first --max-tasks of them; ValueError naming the flag."""
    if args.max_tasks is not None and args.max_tasks < 1:
        raise ValueError(f"--max-tasks must be positive, got {args.max_tasks}")
    options: dict[str, Any] = dict(
        controller="gp-mpc",
        env=args.env,
        split=args.split,
        tasks=args.tasks or "all",
        task_seed=None if args.scenarios is not None else args.seed,
        scenarios=args.scenarios,
        data=args.data,
        preset=args.preset,
        mpc=args.set,
        eval_seed=args.sample_seed,
        figures="none",
    )
    with flags(FLAGS):
        p = prepare(**options)
        ids = p.setup.task_ids
        if args.max_tasks is not None and len(ids) > args.max_tasks:
            p = prepare(**{**options, "tasks": ids[: args.max_tasks]})
    return p


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
        metavar="TASKS",
        help="only these tasks of the split, e.g. 0,3,5, 0-29 (inclusive) or 0:30 (30 excluded); "
        "default all",
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
        p = plan(args)
        s = p.setup
        ids, n_split = s.task_ids, p.split_size
        if args.plot_task is not None and args.plot_task not in ids:
            shown = f"{ids[0]} to {ids[-1]}" if _consecutive(ids) else ",".join(map(str, ids))
            raise ValueError(f"--plot-task {args.plot_task}: not among the tasks run ({shown})")
        plot = ids.index(ids[0] if args.plot_task is None else args.plot_task)
        args.env = s.env_name  # MODULE:NAME registers NAME
        cfg = MPCConfig(**s.mpc)
        first, last = ids[0], ids[-1]
        path = args.out / record_name(args, first, last + 1, n_split, ids)
        settings = record_settings(args, s.scenarios, first, last + 1, cfg, ids)
        probe_out(args.out)  # before the rollout, not after it
        check_replace(path, settings, args.overwrite)
    if failed.code is not None:
        return failed.code
    ev = p.run()
    assert ev.result is not None and ev.stats is not None
    traj: dict[str, Any] = {k: np.asarray(v[0]) for k, v in ev.result.items() if k != "acted_by"}
    tasks = s.tasks
    m = metrics.compute(
        traj["position"], traj["collision"], traj["in_goal"], tasks.goal, s.env_config.robot_radius
    )
    stats: dict[str, Any] = ev.stats
    wall = ev.record["wall_s"]
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
        png = _plot(args, path, s.env_config, tasks, traj, plot, ids[plot])
    if failed.code is not None:
        return failed.code
    which = f"{first} to {last}" if _consecutive(ids) else ",".join(map(str, ids))
    print(f"GP-MPC on {args.env}/{args.split}: {tasks.num_tasks} tasks ({which}), {wall:.1f} s")
    print(metrics_table([("this run", m), ("paper GP-MPC", paper)]))
    print(f"status: {stats['status']}  reasons: {stats['reasons']}")
    if stats["sqp_stops"]:  # why each row's SQP ended (capped: the cap's best iterate was used)
        print(f"SQP ended: {stats['sqp_stops']}  plans from starts: {stats['starts']}")
    if solve_ms.size:
        print(f"solve ms: median {med:.2f}, p95 {p95:.2f}")
    print(f"wrote {path}")
    print(f"wrote {png}")
    return 0


def _consecutive(ids: list[int]) -> bool:
    return ids == list(range(ids[0], ids[-1] + 1))


def record_settings(
    args, scenarios: dict | None, start: int, stop: int, cfg: MPCConfig, ids: list[int]
) -> dict:
    """The record's fields that say what was run (its first fields, in this order)."""
    return {
        "env": args.env,
        "split": args.split,
        # the split's tasks start to stop - 1, or the task numbers when not consecutive
        "tasks": [start, stop] if _consecutive(ids) else ids,
        "data": str(args.data) if args.data else None,
        "scenarios": scenarios,
        "seed": None if args.scenarios is not None else args.seed,
        "sample_seed": args.sample_seed,
        "preset": args.preset,
        "mpc": cfg.to_dict(),
    }


def record_name(args, start: int, stop: int, n_split: int, ids: list[int] | None = None) -> str:
    """The record's file name: ENV_SPLIT, the task range when not the whole split (the task
    numbers `ids` when they are not consecutive), then each setting that is not the default
    (module doc)."""
    name = f"{args.env}_{args.split}"
    if ids is not None and not _consecutive(ids):
        text = "+".join(map(str, ids))
        if len(text) > 40:  # a name the file system takes; the record lists every task
            text = hashlib.sha1(text.encode()).hexdigest()[:12]
        name += f"_tasks{text}"
    elif args.tasks or (start, stop) != (0, n_split):
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


def figure_path(record: Path, task: int) -> Path:
    """The trajectory figure of the split's task `task` beside `record`, named after it (a run of
    other settings, which names its record otherwise, never replaces the figure)."""
    return record.with_name(f"{record.stem}_task{task}.png")


def _plot(args, record: Path, env_config, tasks, traj, i: int, task: int) -> Path:
    """The trajectory of tasks[i], the split's task `task`: its figure's path (`figure_path`)."""
    import jax

    from mpcpearl_jax.envs import save_trajectory

    params = jax.tree_util.tree_map(lambda a: a[i], tasks)
    png = save_trajectory(
        args.env,
        figure_path(record, task),
        params,
        {"GP-MPC": (traj["position"][i], traj["collision"][i])},
        env_config,
        title=f"GP-MPC, {args.env} {args.split} task {task}",
    )
    return png


if __name__ == "__main__":
    sys.exit(main())
