"""Evaluate a trained run (or the GP-MPC baseline) on any task set: metrics, figures, GIFs.

    python -m experiments.evaluate runs/<run> --split ood --animate
    python -m experiments.evaluate runs/<run> --split test --online --seed-index 0
    python -m experiments.evaluate --controller gp-mpc --env restaurant --split val --tasks 0-3
    python -m experiments.evaluate runs/<run> --controller gp-mpc      # the baseline, same tasks
    python -m experiments.evaluate runs/<run> --controller policy+mpc --animate   # as in training
    python -m experiments.evaluate runs/<run> --split val --task-seeds 1-8  # 8 fresh task sets

Controllers:
  policy      the run's policy with the meta-test protocol (MPC off): --episodes adaptation
              episodes, then the evaluated one; or --online (one episode, z re-inferred every
              t_update steps). Needs RUN_DIR (config.json, policy.msgpack, network.json).
  gp-mpc      the risk-aware MPC at every step (the paper's GP-MPC column). With RUN_DIR it runs
              on that run's tasks with its MPC settings; without, on --env with the defaults.
  policy+mpc  one training-style episode per task: z from the prior, stochastic policy, the MPC
              acting on an event with probability --eps (default: the run's eps).
A GrBAL run (`experiments.grbal`) is evaluated with its own controller, as its results.json
(the learned model adapting as it acts, MPPI planning; after its adaptation episodes, or
--online); the MPC options (--controller, --set, --eps), --episodes and --shield do not apply.

With --task-seeds the split is drawn once per task-set seed (fresh crowds for every seed; the
restaurant keeps its eight table layouts) and the metrics are pooled over all those tasks, with
the standard error over tasks and the per-task-seed means; one results.json, no figures
(default out: ...-seeds<A-B>).

Prints SR / TT / CFR / SPL / MGD (mean and per seed, then per task) and how the episodes ended
(`failures`: no contact and goal reached; first contact with a person or with a static obstacle,
goal reached after it or not; out of time; `metrics.first_contact`), and writes results.json,
trajectory figures and, with --animate, one GIF per figure task into --out (default
RUN_DIR/eval/<controller>-<split>[-online], or runs/eval/gp-mpc-<env>-<split>). With every task of
the split and the default --eval-seed, the policy (and GrBAL) numbers are those of the run's
results.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.cli.args import add_task_source_options, env_family
from mpcpearl_jax.cli.errors import one_line_errors
from mpcpearl_jax.cli.output import broken_line, guarded_stdout
from mpcpearl_jax.cli.platform import check_platform
from mpcpearl_jax.cli.stopping import exit_interrupted, stoppable
from mpcpearl_jax.envs import SPLITS, env_names, make_env
from mpcpearl_jax.evaluation.command import (
    FIGURES,
    UsageError,
    check_eval_seed,
    default_out,
    evaluate,
    mpc_overrides,
    parse_indices,
    parse_ranges,
    pooled_record,
    probe_out,
    tables,
    task_setup,
    write_figures,
)
from mpcpearl_jax.evaluation.evaluate import EVAL_SEED
from mpcpearl_jax.evaluation.runners import Setup
from mpcpearl_jax.evaluation.scoring import failure_line
from mpcpearl_jax.mpc.shield import ShieldConfig
from mpcpearl_jax.runfolder import write_json

__all__ = ["UsageError", "main", "make_parser", "parse_indices", "setup"]

CONTROLLERS = ("policy", "gp-mpc", "policy+mpc")
MAX_TASK_SEEDS = 100  # task-set seeds in one command (each one is a full evaluation)


def make_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.evaluate",
        description="Evaluate a trained run, or the GP-MPC baseline, on any task set.",
        epilog="Examples: python -m experiments.evaluate runs/<run> --split ood --animate; "
        "python -m experiments.evaluate --controller gp-mpc --env restaurant --split val",
    )
    p.add_argument("run", nargs="?", type=Path, help="run directory (config.json + policy.msgpack)")
    p.add_argument(
        "--controller",
        choices=CONTROLLERS,
        default="policy",
        help="policy: meta-test protocol (default); gp-mpc: the MPC alone; policy+mpc: "
        "training-style episodes with MPC infusion",
    )
    p.add_argument("--env", help="task family when there is no RUN_DIR (default restaurant)")
    p.add_argument("--split", choices=SPLITS, default="test", help="task set (default test)")
    p.add_argument("--task-seed", type=int, help="task-set seed (default: the run's, or 0)")
    p.add_argument(
        "--task-seeds",
        help="several task-set seeds, e.g. 1-8 or 1,5: the split drawn with each, pooled into "
        "one mean with its standard error over tasks (a lower-variance estimate; no figures)",
    )
    add_task_source_options(p, from_run=True)
    p.add_argument(
        "--perturb",
        default="none",
        metavar="delay=K,speed=S",
        help="re-time the people on their paths (mpcpearl_jax.envs.perturb): delay=K holds "
        "everyone at the start K more steps, speed=S follows the paths S times as fast; both "
        "combine, e.g. delay=3,speed=1.3 (default none)",
    )
    p.add_argument("--online", action="store_true", help="online adaptation (one episode)")
    p.add_argument(
        "--episodes", type=int, help="adaptation episodes before the evaluated one (default: run's)"
    )
    p.add_argument("--seed-index", type=int, help="evaluate this seed only (default: all seeds)")
    p.add_argument(
        "--tasks", default="all", help="task indices of the split, e.g. 0,3,5 or 0-3 (default all)"
    )
    p.add_argument(
        "--figures",
        help=f"tasks with a trajectory figure and GIF (default: the first {FIGURES} evaluated; "
        "'none' for none)",
    )
    p.add_argument("--animate", action="store_true", help="also a GIF of each figure task")
    p.add_argument(
        "--eps", type=float, help="policy+mpc: MPC probability on an event (default: run's)"
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="MPC controllers: override an MPCConfig field (repeatable)",
    )
    p.add_argument(
        "--shield",
        action="store_true",
        help="policy: execute the actions through the test-time safety shield (extension, "
        "mpcpearl_jax.mpc.shield; docs/extensions.md)",
    )
    p.add_argument(
        "--shield-margin",
        type=float,
        default=None,
        help=f"--shield: clearance in metres beyond contact (default {ShieldConfig.margin:g})",
    )
    p.add_argument(
        "--shield-lookahead",
        type=int,
        default=None,
        help=f"--shield: steps each candidate is held for the check "
        f"(default {ShieldConfig.lookahead})",
    )
    p.add_argument("--eval-seed", type=int, default=EVAL_SEED, help="PRNG seed of the evaluation")
    p.add_argument("--out", type=Path, help="output folder")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an earlier evaluation's results.json in --out (a run's own folder is "
        "never an output folder)",
    )
    return p


def _task_setup(args: argparse.Namespace, cfg: Any, env: Any, env_name: str, data: str | None):
    """`task_setup` with the options of the command line `args`."""
    return task_setup(
        cfg,
        env,
        env_name,
        data,
        args.split,
        task_seed=args.task_seed,
        task_seeds=args.task_seeds,
        scenarios=args.scenarios,
        tasks=args.tasks,
        figures=args.figures,
        perturb=args.perturb,
    )


def _grbal_setup(args: argparse.Namespace) -> Setup:
    """A GrBAL run (`experiments.grbal`): its own controller, the learned model adapted as it
    acts, planned with MPPI (the protocol of its results.json)."""
    from mpcpearl_jax.grbal.run import load_model

    given = [
        f
        for f, v in (
            ("--controller", args.controller != "policy"),
            ("--set", args.set),
            ("--eps", args.eps is not None),
            ("--episodes", args.episodes is not None),
            ("--shield", args.shield),
            ("--env", args.env),
        )
        if v
    ]
    if given:
        raise UsageError(f"{given[0]} does not apply to a GrBAL run (it is evaluated as trained)")
    data = str(args.data) if args.data else None
    try:
        trainer, saved = load_model(args.run, data=data)
    except (ValueError, OSError) as e:  # a bad config, data file or task option
        raise UsageError(f"{args.run}: {e}") from e
    cfg = trainer.cfg
    if cfg.data is not None and not Path(cfg.data).is_file():
        raise UsageError(
            f"data file {cfg.data} does not exist (the run's data file; pass --data PATH)"
        )
    seeds = cfg.seeds
    if args.seed_index is not None and not 0 <= args.seed_index < seeds:
        raise UsageError(f"--seed-index {args.seed_index}: the run has {seeds} seed(s)")
    seed_ids = list(range(seeds)) if args.seed_index is None else [args.seed_index]
    saved = jax.tree_util.tree_map(lambda x: np.asarray(x)[np.asarray(seed_ids)], saved)
    task_seed, scenarios, tasks, task_ids, figure_ids, perturbation = _task_setup(
        args, cfg, trainer.env, cfg.env, cfg.data
    )
    out = args.out or default_out(
        args.run, "grbal", args.split, args.online, scenarios, perturbation
    )
    return Setup(
        controller="grbal",
        env_name=cfg.env,
        env_config=trainer.env.config,
        split=args.split,
        task_seed=task_seed,
        data=cfg.data,
        tasks=tasks,
        task_ids=task_ids,
        figure_ids=figure_ids,
        out=out,
        label="GrBAL",
        run=args.run,
        run_config=cfg,
        seed_ids=seed_ids,
        scenarios=scenarios,
        perturbation=perturbation.label,
        grbal=(trainer, saved),
    )


def setup(args: argparse.Namespace) -> Setup:
    """Resolve the command line; raises UsageError (and CheckpointError) with a one-line reason."""
    from mpcpearl_jax.deploy.policy import load_policy
    from mpcpearl_jax.envs import mpc_defaults
    from mpcpearl_jax.evaluation.report import run_label
    from mpcpearl_jax.grbal.run import is_grbal_run
    from mpcpearl_jax.runfolder import load_config

    ctrl = args.controller
    cfg = None
    if args.run is not None:
        if not args.run.is_dir():
            raise UsageError(f"{args.run}: no such directory")
        if is_grbal_run(args.run):
            return _grbal_setup(args)
        cfg = load_config(args.run)  # CheckpointError: not a run directory
    elif ctrl != "gp-mpc":
        raise UsageError(f"--controller {ctrl} needs a run directory (RUN_DIR)")
    if ctrl == "gp-mpc" and (args.online or args.episodes is not None):
        raise UsageError("--online and --episodes apply to the policy (GP-MPC does not adapt)")
    if ctrl != "policy" and args.online:
        raise UsageError(f"--online applies to --controller policy, not {ctrl}")
    if ctrl == "gp-mpc" and args.eps is not None:
        raise UsageError("--eps applies to --controller policy+mpc (GP-MPC acts on every step)")
    if ctrl == "policy" and (args.set or args.eps is not None):
        raise UsageError("--set and --eps apply to the MPC controllers (gp-mpc, policy+mpc)")
    shield = None
    shield_given = args.shield_margin is not None or args.shield_lookahead is not None
    if shield_given and not args.shield:
        raise UsageError("--shield-margin and --shield-lookahead need --shield")
    if args.shield:
        if ctrl != "policy":
            raise UsageError(f"--shield applies to --controller policy, not {ctrl}")
        try:
            given = {"margin": args.shield_margin, "lookahead": args.shield_lookahead}
            shield = ShieldConfig(**{k: v for k, v in given.items() if v is not None})
        except ValueError as e:
            raise UsageError(str(e).replace("shield.", "--shield-", 1)) from e
    if args.episodes is not None and args.episodes < 0:
        raise UsageError(f"--episodes {args.episodes}: must be >= 0")
    if args.online and args.episodes is not None:
        raise UsageError(
            "--episodes counts the adaptation episodes before the scored one; --online adapts "
            "within the one scored episode: give one of them"
        )
    check_eval_seed(args.eval_seed)
    family = env_family(args.env, UsageError) if args.env else None  # MODULE:NAME registers NAME
    env_name = cfg.env if cfg else (family or "restaurant")
    if cfg and family and family != cfg.env:
        raise UsageError(f"--env {args.env}: the run {args.run} was trained on {cfg.env}")
    data = str(args.data) if args.data else (cfg.data if cfg else None)
    if data is not None and not Path(data).is_file():
        hint = "" if args.data else " (the run's data file; pass --data PATH)"
        raise UsageError(f"data file {data} does not exist{hint}")
    overrides = dict(cfg.env_overrides) if cfg else {}
    if cfg and env_name not in env_names():
        raise UsageError(
            f"{args.run}: trained on the task family {env_name!r}, not registered here: pass "
            f"--env MODULE:{env_name}, MODULE the module that registers it "
            "(docs/custom_tasks.md)"
        )
    try:
        env = make_env(env_name, **overrides)
    except ValueError as e:
        raise UsageError(str(e)) from e
    task_seed, scenarios, tasks, task_ids, figure_ids, perturbation = _task_setup(
        args, cfg, env, env_name, data
    )

    base_mpc = cfg.mpc.to_dict() if cfg else mpc_defaults(env_name)
    mpc = mpc_overrides(args.set, base_mpc) if ctrl != "policy" else {}
    policies, seed_ids, label, eps = [], [], "GP-MPC", None
    if ctrl != "gp-mpc":
        seeds = cfg.seeds
        if args.seed_index is not None and not 0 <= args.seed_index < seeds:
            raise UsageError(f"--seed-index {args.seed_index}: the run has {seeds} seed(s)")
        seed_ids = list(range(seeds)) if args.seed_index is None else [args.seed_index]
        try:  # CheckpointError (no or corrupt policy.msgpack) goes to the caller as it is
            policies = [load_policy(args.run, s) for s in seed_ids]
        except (ValueError, TypeError, OSError) as e:
            raise UsageError(f"{args.run}: cannot load the policy: {e}") from e
        label = run_label(cfg)
        if ctrl == "policy+mpc":
            eps = cfg.train.eps if args.eps is None else args.eps
            if not 0.0 <= eps <= 1.0:
                raise UsageError(f"--eps {eps}: must be in [0, 1]")
            label = f"{label} + MPC (eps {eps:g})"
        if shield is not None:
            label = f"{label} + shield (margin {shield.margin:g} m, lookahead {shield.lookahead})"
    elif args.seed_index is not None:
        raise UsageError("--seed-index applies to a run's policy, not to gp-mpc")
    out = args.out
    if out is None and args.run is not None:
        name = f"{ctrl}-shield" if shield is not None else ctrl
        out = default_out(args.run, name, args.split, args.online, scenarios, perturbation)
    elif out is None:
        split_name = f"scenarios-{args.split}" if scenarios is not None else args.split
        out = Path("runs") / "eval" / f"gp-mpc-{env_name}-{split_name}{perturbation.folder_suffix}"
    return Setup(
        controller=ctrl,
        env_name=env_name,
        env_config=env.config,
        split=args.split,
        task_seed=task_seed,
        data=data,
        tasks=tasks,
        task_ids=task_ids,
        figure_ids=figure_ids,
        out=out,
        label=label,
        run=args.run,
        run_config=cfg,
        policies=policies,
        seed_ids=seed_ids,
        mpc=mpc,
        eps=eps,
        shield=shield,
        scenarios=scenarios,
        perturbation=perturbation.label,
    )


def main_task_seeds(args: argparse.Namespace) -> int:
    """--task-seeds: the controller on the split of each task-set seed, pooled."""
    import copy

    if args.task_seed is not None:
        print("error: give --task-seed or --task-seeds, not both", file=sys.stderr)
        return 2
    if args.figures not in (None, "none") or args.animate:
        print("error: --task-seeds makes no figures (drop --figures/--animate)", file=sys.stderr)
        return 2
    records, s, out = [], None, args.out
    with one_line_errors(interrupted=None) as failed:
        hint = " in one command (the project's protocol uses 8: 1-8)"
        text = args.task_seeds.strip()
        seeds = sorted(parse_ranges(text, "--task-seeds", MAX_TASK_SEEDS, "task sets", hint))
        span = (
            f"{seeds[0]}-{seeds[-1]}"
            if seeds == list(range(seeds[0], seeds[-1] + 1))
            else ",".join(map(str, seeds))
        )
        for ts in seeds:
            a = copy.copy(args)
            a.task_seed, a.figures = ts, "none"
            s = setup(a)
            if ts == seeds[0]:  # the output folder, checked before the first evaluation
                out = out or s.out.parent / f"{s.out.name}-seeds{span.replace(',', '_')}"
                probe_out(out, args.overwrite)
            record, _ = evaluate(s, a.eval_seed, a.episodes, a.online)
            records.append(record)
            print(
                f"[evaluate] task seed {ts}: {len(s.task_ids)} task(s), "
                f"SR {record['metrics']['SR']:.2f} CFR {record['metrics']['CFR']:.2f}",
                flush=True,
            )
    if failed.code is not None:
        return failed.code
    summary = pooled_record(s, seeds, records)
    with one_line_errors(interrupted=None) as failed:  # written before anything is printed
        write_json(out / "results.json", summary)
    if failed.code is not None:
        return failed.code
    n_tasks, pool, fails = summary["num_tasks"], summary["pooled"], summary["failures"]
    protocol = records[0]["protocol"]
    crowd = "" if s.perturbation == "none" else f", crowd perturbed {s.perturbation}"
    print(
        f"{s.label}: {s.env_name}/{s.split}, task seeds {span} ({n_tasks} tasks){crowd}, {protocol}"
    )
    print("| metric | mean | s.e. | per task seed |\n|---|---|---|---|")
    for k, v in pool.items():
        per = " ".join(f"{x:.2f}" for x in v["per_task_seed"])
        print(f"| {k} | {v['mean']:.2f} | {v['se']:.2f} | {per} |")
    print(failure_line(fails))
    print(f"wrote {out / 'results.json'}")
    return 0


@stoppable
def main(argv: list[str] | None = None) -> int:
    """The command; a stop signal (Ctrl-C, SIGTERM, SIGHUP) ends it with one line and exit code
    128 + the signal. Nothing is lost: an evaluation saves only at its end, so the same command
    (with --overwrite where its results.json was already written) starts it again. A standard
    output that breaks (`| head`, a full disk) loses nothing: results.json and the figures are
    written first, and the command ends with one line on stderr and exit code 2."""
    try:
        with guarded_stdout() as stdout:
            code = _main(argv)
    except KeyboardInterrupt:
        exit_interrupted(
            "interrupted before the evaluation finished; run the same command again "
            "(with --overwrite if --out already holds its results.json)"
        )
    if stdout.broken is not None:
        what = "results.json and the figures are written" if code == 0 else "see above"
        print(broken_line(stdout.broken, what), file=sys.stderr, flush=True)
        return code or 2
    return code


def _main(argv: list[str] | None) -> int:
    args = make_parser().parse_args(argv)
    with one_line_errors(interrupted=None) as failed:
        check_platform()  # JAX_PLATFORMS naming a platform this machine lacks: one line
    if failed.code is not None:
        return failed.code
    if args.task_seeds is not None:
        return main_task_seeds(args)
    with one_line_errors(interrupted=None) as failed:
        s = setup(args)
        probe_out(s.out, args.overwrite)  # before the evaluation, not after it
    if failed.code is not None:
        return failed.code
    n_seeds = len(s.seed_ids) or 1
    source = "the paper's scenarios" if s.scenarios else f"task seed {s.task_seed}"
    if s.perturbation != "none":
        source += f", crowd perturbed {s.perturbation}"
    print(
        f"[evaluate] {s.label}: {s.env_name}/{s.split} ({source}), "
        f"{len(s.task_ids)} task(s), {n_seeds} seed(s), controller {s.controller}",
        flush=True,
    )
    record, result = evaluate(s, args.eval_seed, args.episodes, args.online)
    with one_line_errors(interrupted=None) as failed:  # a full disk, or --out changed under it
        write_json(s.out / "results.json", record)  # written before anything is printed
        written = write_figures(s, result, args.animate)
    if failed.code is not None:
        return failed.code
    print(f"{record['protocol']}; {record['wall_s']:.1f} s", flush=True)
    print(tables(record))
    print(failure_line(record["failures"]))
    print(f"wrote {s.out / 'results.json'}" + "".join(f", {p.name}" for p in written))
    return 0
