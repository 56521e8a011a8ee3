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
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import jax
import numpy as np

from experiments.common import (
    add_task_source_options,
    env_family,
    exit_interrupted,
    one_line_errors,
)
from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.envs import SPLITS, env_names, make_env, tasks_for
from mpcpearl_jax.envs.perturb import parse_perturbation, perturb_tasks
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.evaluation.evaluate import EVAL_SEED
from mpcpearl_jax.evaluation.metrics import METRIC_NAMES
from mpcpearl_jax.evaluation.runners import (
    Setup,
    run_gp_mpc,
    run_policy,
    run_policy_mpc,
)
from mpcpearl_jax.evaluation.scoring import failure_line, failures, per_task_metrics, pooled
from mpcpearl_jax.mpc.shield import ShieldConfig
from mpcpearl_jax.runfolder import RUN_RECORDS, write_json
from mpcpearl_jax.training.stopping import stoppable
from mpcpearl_jax.validate import unwritable_folder

CONTROLLERS = ("policy", "gp-mpc", "policy+mpc")
MAX_TASK_SEEDS = 100  # task-set seeds in one command (each one is a full evaluation)
FIGURES = 4  # default number of tasks with a figure (and a GIF with --animate)


class UsageError(ValueError):
    """A bad command line or input file; reported as one line, exit status 2."""


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


def _parse_spans(text: str, what: str) -> list[tuple[int, int]]:
    """'0,3,5' | '0-3' (inclusive) | a mix -> its (lo, hi) spans, sorted and merged, never
    expanded (a span may be billions long); UsageError for an empty or reversed range (5-1) and
    for nothing at all."""
    spans: list[tuple[int, int]] = []
    for part in text.split(","):
        a, dash, b = part.partition("-")
        try:
            lo, hi = int(a), (int(b) if dash else int(a))
        except ValueError:
            raise UsageError(f"{what} {text!r}: expected numbers like 0,3,5 or 0-3") from None
        if hi < lo:
            raise UsageError(
                f"{what} {text!r}: the range {part.strip()} is reversed (give A-B, A <= B)"
            )
        spans.append((lo, hi))
    merged: list[tuple[int, int]] = []
    for lo, hi in sorted(spans):
        if merged and lo <= merged[-1][1] + 1:
            merged[-1] = (merged[-1][0], max(merged[-1][1], hi))
        else:
            merged.append((lo, hi))
    return merged


def _count(spans: list[tuple[int, int]]) -> int:
    return sum(hi - lo + 1 for lo, hi in spans)


def _parse_ranges(
    text: str, what: str, cap: int | None = None, unit: str = "values", hint: str = ""
) -> set[int]:
    """The integers of '0,3,5' | '0-3' | a mix (`_parse_spans`); with `cap`, UsageError when
    there are more than `cap` of them (`unit`, then `hint`), checked before anything is
    expanded."""
    spans = _parse_spans(text, what)
    n = _count(spans)
    if cap is not None and n > cap:
        raise UsageError(f"{what} {text}: {n} {unit}; at most {cap}{hint}")
    return {i for lo, hi in spans for i in range(lo, hi + 1)}


def check_eval_seed(seed: int) -> None:
    """UsageError unless `seed` makes a PRNG key (an integer that fits 64 bits)."""
    try:
        jax.random.PRNGKey(seed)
    except (OverflowError, ValueError, TypeError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise UsageError(f"--eval-seed {seed}: not a PRNG seed ({first})") from None


def probe_out(out: Path, overwrite: bool = False) -> None:
    """Create the output folder and prove it writable before any work (a probe file written and
    removed); UsageError naming it otherwise. A run's folder (it holds a run's records) is never
    an output folder, and an earlier evaluation's results.json is replaced only with
    `overwrite`."""
    records = [name for name in RUN_RECORDS[:4] if (out / name).exists()]
    if records:
        raise UsageError(
            f"--out {out}: a run's folder (it holds {', '.join(records)}); an evaluation never "
            f"writes over a run's records: choose another --out, e.g. {out / 'eval' / 'NAME'}"
        )
    if (out / "results.json").exists() and not overwrite:
        raise UsageError(
            f"--out {out}: holds an earlier evaluation's results.json; pass --overwrite to "
            "replace it, or choose another --out"
        )
    why = unwritable_folder(out)
    if why is not None:
        raise UsageError(f"--out {out}: not writable ({why}); choose another --out")


def parse_indices(text: str, n: int, what: str) -> list[int]:
    """'all' | 'none' | '0,3,5' | '0-3' (inclusive) | a mix -> sorted unique indices < n."""
    text = text.strip().lower()
    if text == "all":
        return list(range(n))
    if text in ("none", ""):
        return []
    spans = _parse_spans(text, what)
    beyond = [(max(lo, n), hi) for lo, hi in spans if hi >= n]  # checked before expanding
    if beyond:
        count = _count(beyond)
        first = [i for lo, hi in beyond for i in range(lo, min(hi, lo + 5) + 1)][:5]
        shown = first if count <= 5 else f"{first[:3]} and {count - 3} more"
        raise UsageError(
            f"{what}: task(s) {shown} out of range; the split has {n} tasks (0-{n - 1})"
        )
    return sorted(i for lo, hi in spans for i in range(lo, hi + 1))


def _mpc_overrides(items: list[str], base: dict) -> dict:
    """The MPCConfig fields `base` with the --set FIELD=VALUE `items` on top (read by each
    field's type, `mpcpearl_jax.config.parse_override`), checked; UsageError in one line."""
    from mpcpearl_jax.config import mpc_config, parse_override
    from mpcpearl_jax.mpc import MPCConfig

    out = dict(base)
    try:
        for item in items:
            _, field, value = parse_override(item, {"": MPCConfig})
            out[field] = value
    except ConfigError as e:
        raise UsageError(str(e)) from e
    try:
        mpc_config(out)  # the one check of MPCConfig fields and values
    except ValueError as e:
        raise UsageError(f"--set: {e}") from e
    return out


def _task_setup(args: argparse.Namespace, cfg: Any, env: Any, env_name: str, data: str | None):
    """The evaluated tasks of `args` for a run config: (task seed, scenario source, tasks, task
    ids, figure ids, perturbation)."""
    task_seed = args.task_seed if args.task_seed is not None else (cfg.task_seed if cfg else 0)
    source = (cfg or ExperimentConfig(env=env_name)).replace(data=data)
    scenarios = _scenario_source(args, cfg, env_name, source.task_options)
    if scenarios is not None:  # the paper's scenarios, in place of the run's task source
        source = source.replace(data=None, task_options=scenarios)
    try:
        all_tasks = tasks_for(source, args.split, config=env.config, seed=task_seed)
    except (ValueError, TypeError, OSError) as e:
        if isinstance(e, OSError) and scenarios is None:
            raise
        raise UsageError(f"{env_name} --split {args.split}: {e}") from e
    n = all_tasks.num_tasks
    task_ids = parse_indices(args.tasks, n, "--tasks")
    if not task_ids:
        raise UsageError("--tasks: no task selected")
    if args.figures is None:
        figure_ids = task_ids[:FIGURES]
    else:
        figure_ids = parse_indices(args.figures, n, "--figures")
        missing = sorted(set(figure_ids) - set(task_ids))
        if missing:
            raise UsageError(f"--figures: task(s) {missing} are not evaluated (see --tasks)")
    tasks = jax.tree_util.tree_map(lambda x: x[np.asarray(task_ids)], all_tasks)
    try:
        perturbation = parse_perturbation(args.perturb)
    except ValueError as e:
        raise UsageError(str(e)) from e
    return (
        task_seed,
        scenarios,
        perturb_tasks(tasks, perturbation),
        task_ids,
        figure_ids,
        perturbation,
    )


def _default_out(args: argparse.Namespace, name: str, scenarios: Any, perturbation: Any) -> Path:
    split_name = f"scenarios-{args.split}" if scenarios is not None else args.split
    split_name += perturbation.folder_suffix
    return args.run / "eval" / (f"{name}-{split_name}" + ("-online" if args.online else ""))


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
    out = args.out or _default_out(args, "grbal", scenarios, perturbation)
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
    mpc = _mpc_overrides(args.set, base_mpc) if ctrl != "policy" else {}
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
        out = _default_out(args, name, scenarios, perturbation)
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


def _scenario_source(
    args: argparse.Namespace, cfg: Any, env_name: str, task_options: dict
) -> dict | None:
    """The task options of the paper's scenarios when they are the task source (--scenarios, or
    the run trained on them), else None. A run that trained on every training scenario is not
    scored on the val split (its tasks 150-179 were training tasks)."""
    from mpcpearl_jax.envs.restaurant.scenarios import check_val_split, scenario_options

    if args.scenarios is None and not task_options.get("scenarios"):
        return None
    if env_name != "restaurant":
        raise UsageError(f"--scenarios: the paper's scenarios are restaurant tasks, not {env_name}")
    if args.task_seed is not None or args.task_seeds is not None:
        raise UsageError("--task-seed(s): the paper's scenarios are one fixed set of tasks")
    trained = dict(cfg.task_options) if cfg else {}
    try:
        if args.scenarios is not None:
            out = scenario_options(args.scenarios)
        else:  # the run's own scenarios: the same files it recorded
            out = {k: v for k, v in task_options.items() if k in ("scenarios", "scenario_sha256")}
        check_val_split(trained, args.split)
    except (ValueError, OSError) as e:
        raise UsageError(f"--scenarios: {e}") from e
    return out


# ---------------------------------------------------------------------------------- output
def tables(record: dict) -> str:
    """Markdown: metrics (mean, per seed), then per task (mean over the evaluated seeds)."""
    seeds = record["seeds"]
    per_seed = record["per_seed"]
    head = ["metric", "mean"] + ([f"seed {s}" for s in seeds] if len(seeds) > 1 else [])
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for k in (*METRIC_NAMES, "return"):
        cells = [f"{record['metrics'][k]:.2f}"]
        if len(seeds) > 1:
            cells += [f"{v:.2f}" for v in per_seed[k]]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    pt = {k: np.asarray(v) for k, v in record["per_task"].items()}
    note = f" (mean over {len(seeds)} seeds)" if len(seeds) > 1 else ""
    lines += ["", f"Per task{note}:", ""]
    cols = ("SR", "CFR", "TT", "SPL", "MGD", "return")
    lines += ["| task | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for j, t in enumerate(record["tasks"]):
        vals = " | ".join(f"{pt[c][:, j].mean():.2f}" for c in cols)
        lines.append(f"| {t} | {vals} |")
    return "\n".join(lines)


def write_figures(s: Setup, result: dict, animate: bool) -> list[Path]:
    """A trajectory PNG (and a GIF with animate) of the first evaluated seed on each figure
    task, in the family's style (its registered viewer)."""
    from mpcpearl_jax.envs import save_trajectory
    from mpcpearl_jax.evaluation import animate as anim_lib

    written = []
    who = f"seed {s.seed_ids[0]}" if s.seed_ids else s.label
    for t in s.figure_ids:
        j = s.task_ids.index(t)
        task = jax.tree_util.tree_map(lambda x, j=j: np.asarray(x)[j], s.tasks)
        pos, col = np.asarray(result["position"][0, j]), np.asarray(result["collision"][0, j])
        title = f"{s.label}{f' ({who})' if s.seed_ids else ''}, {s.env_name} {s.split} task {t}"
        png = s.out / f"trajectory_{s.split}{t}.png"
        save_trajectory(s.env_name, png, task, {who: (pos, col)}, s.env_config, title)
        written.append(png)
        if animate:
            gif = anim_lib.animate_result(
                s.out / f"episode_{s.split}{t}.gif", result, s.tasks, s.env_config, j, 0, title
            )
            written.append(gif)
    return written


def evaluate(args: argparse.Namespace, s: Setup) -> tuple[dict, dict]:
    """Run the controller on the tasks; -> (record for results.json, raw arrays [S, N, ...])."""
    from mpcpearl_jax.evaluation import evaluate as eval_lib

    key = jax.random.PRNGKey(args.eval_seed)
    stats = None
    t0 = time.perf_counter()
    if s.controller == "policy":
        episodes = (
            s.run_config.train.eval_adapt_episodes if args.episodes is None else args.episodes
        )
        protocol = "online" if args.online else f"after {episodes} adaptation episode(s)"
        result = run_policy(s, key, episodes, args.online)
    elif s.controller == "gp-mpc":
        protocol = "MPC at every step"
        result, stats = run_gp_mpc(s, key)
    elif s.controller == "grbal":
        trainer, saved = s.grbal
        episodes = s.run_config.grbal.eval_adapt_episodes
        protocol = "online" if args.online else f"after {episodes} adaptation episode(s)"
        raw = trainer.rollouts(saved["model"], saved["norm"], s.tasks, key)
        result = raw["online" if args.online else "adapt"]
    else:
        protocol = f"training-style episode: prior z, MPC on an event with probability {s.eps:g}"
        result, stats = run_policy_mpc(s, key, s.eps)
    wall = time.perf_counter() - t0
    summary = eval_lib.summarize(result, s.tasks, s.env_config.robot_radius)
    record: dict[str, Any] = {
        "label": s.label,
        "controller": s.controller,
        "run": str(s.run) if s.run else None,
        "env": s.env_name,
        "split": s.split,
        "task_seed": None if s.scenarios else s.task_seed,
        "data": s.data,
        "scenarios": s.scenarios,
        "perturbation": s.perturbation,
        "protocol": protocol,
        "eval_seed": args.eval_seed,
        "seeds": s.seed_ids or [0],
        "tasks": s.task_ids,
        "metrics": {k: v for k, v in summary.items() if not k.endswith("_per_seed")},
        "per_seed": {
            k[: -len("_per_seed")]: v for k, v in summary.items() if k.endswith("_per_seed")
        },
        "per_task": per_task_metrics(result, s.tasks, s.env_config),
        "wall_s": wall,
    }
    if s.controller not in ("policy", "grbal"):
        record["mpc"] = s.mpc
        if s.controller == "policy+mpc":
            record["eps"] = s.eps
        record["mpc_share"] = float(np.mean(result["used_mpc"]))
        record["mpc_status"] = dict(stats["status"])
        record["mpc_reasons"] = dict(stats["reasons"])
    if s.controller in ("policy", "grbal"):
        record["episodes"] = 1 if args.online else episodes + 1
        if s.shield is not None:
            record["shield"] = asdict(s.shield)
            record["shield_rate"] = float(np.mean(result["shielded"]))
    record["failures"] = failures([record["per_task"]])
    return record, result


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
        seeds = sorted(_parse_ranges(text, "--task-seeds", MAX_TASK_SEEDS, "task sets", hint))
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
            record, _ = evaluate(a, s)
            records.append(record)
            print(
                f"[evaluate] task seed {ts}: {len(s.task_ids)} task(s), "
                f"SR {record['metrics']['SR']:.2f} CFR {record['metrics']['CFR']:.2f}",
                flush=True,
            )
    if failed.code is not None:
        return failed.code
    n_tasks = sum(len(r["tasks"]) for r in records)
    pool = pooled(records)
    protocol = records[0]["protocol"]
    crowd = "" if s.perturbation == "none" else f", crowd perturbed {s.perturbation}"
    print(
        f"{s.label}: {s.env_name}/{s.split}, task seeds {span} ({n_tasks} tasks){crowd}, {protocol}"
    )
    print("| metric | mean | s.e. | per task seed |\n|---|---|---|---|")
    for k, v in pool.items():
        per = " ".join(f"{x:.2f}" for x in v["per_task_seed"])
        print(f"| {k} | {v['mean']:.2f} | {v['se']:.2f} | {per} |")
    fails = failures([r["per_task"] for r in records])
    print(failure_line(fails))
    summary = {
        "label": s.label,
        "split": s.split,
        "perturbation": s.perturbation,
        "task_seeds": seeds,
        "num_tasks": n_tasks,
        "pooled": pool,
        "failures": fails,
        "records": records,
    }
    with one_line_errors(interrupted=None) as failed:
        write_json(out / "results.json", summary)
    if failed.code is not None:
        return failed.code
    print(f"wrote {out / 'results.json'}")
    return 0


@stoppable
def main(argv: list[str] | None = None) -> int:
    """The command; a stop signal (Ctrl-C, SIGTERM, SIGHUP) ends it with one line and exit code
    128 + the signal. Nothing is lost: an evaluation saves only at its end, so the same command
    (with --overwrite where its results.json was already written) starts it again."""
    try:
        return _main(argv)
    except KeyboardInterrupt:
        exit_interrupted(
            "interrupted before the evaluation finished; run the same command again "
            "(with --overwrite if --out already holds its results.json)"
        )


def _main(argv: list[str] | None) -> int:
    args = make_parser().parse_args(argv)

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
    record, result = evaluate(args, s)
    print(f"{record['protocol']}; {record['wall_s']:.1f} s", flush=True)
    print(tables(record))
    print(failure_line(record["failures"]))
    with one_line_errors(interrupted=None) as failed:  # a full disk, or --out changed under it
        write_json(s.out / "results.json", record)
        written = write_figures(s, result, args.animate)
    if failed.code is not None:
        return failed.code
    print(f"wrote {s.out / 'results.json'}" + "".join(f", {p.name}" for p in written))
    return 0


if __name__ == "__main__":
    sys.exit(main())
