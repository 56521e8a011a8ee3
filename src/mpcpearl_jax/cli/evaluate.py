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
import contextlib
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mpcpearl_jax.api.evaluate import CONTROLLERS, MAX_TASK_SEEDS, Plan, prepare
from mpcpearl_jax.cli.args import add_task_source_options
from mpcpearl_jax.cli.errors import one_line_errors
from mpcpearl_jax.cli.output import broken_line, guarded_stdout
from mpcpearl_jax.cli.platform import check_platform
from mpcpearl_jax.cli.stopping import exit_interrupted, stoppable
from mpcpearl_jax.envs import SPLITS
from mpcpearl_jax.evaluation import plan as plan_lib
from mpcpearl_jax.evaluation.evaluate import EVAL_SEED
from mpcpearl_jax.evaluation.metrics import METRIC_NAMES
from mpcpearl_jax.evaluation.plan import FIGURES, EvaluationError
from mpcpearl_jax.evaluation.runners import Setup
from mpcpearl_jax.evaluation.scoring import failure_line
from mpcpearl_jax.mpc.shield import ShieldConfig

__all__ = ["MAX_TASK_SEEDS", "UsageError", "main", "make_parser", "parse_indices", "plan", "setup"]


class UsageError(ValueError):
    """A bad command line or input file; reported as one line, exit status 2."""


FLAGS = {"run": "RUN_DIR", "mpc": "--set"}  # where a flag is not --NAME


@contextlib.contextmanager
def flags(names: Mapping[str, str] = FLAGS) -> Iterator[None]:
    """An `EvaluationError` raised again as a UsageError naming the command line's flags (by
    `names`, else --NAME), not the keyword arguments."""
    try:
        yield
    except EvaluationError as e:
        raise UsageError(e.spelled(lambda n: names.get(n, "--" + n.replace("_", "-")))) from e


def parse_indices(text: str, n: int, what: str) -> list[int]:
    """The task indices < n of '0,3,5' | '0-3' | '0:4' | 'all' | 'none' (`what`: the flag);
    UsageError naming it."""
    with flags():
        return plan_lib.parse_indices(text, n, what.lstrip("-").replace("-", "_"))


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
        "--tasks",
        default="all",
        help="task indices of the split, e.g. 0,3,5, 0-3 (inclusive) or 0:30 (30 excluded); "
        "default all",
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


def options(args: argparse.Namespace) -> dict[str, Any]:
    """The keyword arguments of `mpcpearl_jax.evaluate` that the command line `args` gives."""
    shield: bool | ShieldConfig = False
    shield_given = args.shield_margin is not None or args.shield_lookahead is not None
    if shield_given and not args.shield:
        raise UsageError("--shield-margin and --shield-lookahead need --shield")
    if args.shield:
        if args.controller != "policy":
            raise UsageError(f"--shield applies to --controller policy, not {args.controller}")
        try:
            given = {"margin": args.shield_margin, "lookahead": args.shield_lookahead}
            shield = ShieldConfig(**{k: v for k, v in given.items() if v is not None})
        except ValueError as e:
            raise UsageError(str(e).replace("shield.", "--shield-", 1)) from e
    return {
        "controller": args.controller,
        "env": args.env,
        "split": args.split,
        "tasks": args.tasks,
        "task_seed": args.task_seed,
        "task_seeds": args.task_seeds,
        "scenarios": args.scenarios,
        "data": args.data,
        "perturb": args.perturb,
        "episodes": args.episodes,
        "online": args.online,
        "seed_index": args.seed_index,
        "shield": shield,
        "eps": args.eps,
        "mpc": args.set,
        "eval_seed": args.eval_seed,
        "figures": args.figures,
        "animate": args.animate,
    }


def plan(args: argparse.Namespace) -> Plan:
    """The evaluation the command line `args` asks for, checked, writing into --out (default:
    RUN_DIR/eval/..., see the module doc); UsageError (and CheckpointError) in one line."""
    with flags():
        p = prepare(args.run, **options(args))
        return p.writing_to(args.out or p.default_out, args.overwrite)


def setup(args: argparse.Namespace) -> Setup:
    """The (first) task set's resolved setup of the command line `args`, nothing written."""
    with flags():
        return prepare(args.run, **options(args)).setup


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


def _print_task_set(ts: int, record: dict) -> None:
    n, m = len(record["tasks"]), record["metrics"]
    print(
        f"[evaluate] task seed {ts}: {n} task(s), SR {m['SR']:.2f} CFR {m['CFR']:.2f}", flush=True
    )


def _print_pooled(p: Plan, summary: dict) -> None:
    s = p.setups[-1]
    n_tasks, pool, fails = summary["num_tasks"], summary["pooled"], summary["failures"]
    protocol = summary["records"][0]["protocol"]
    crowd = "" if s.perturbation == "none" else f", crowd perturbed {s.perturbation}"
    print(
        f"{s.label}: {s.env_name}/{s.split}, task seeds {p.span} ({n_tasks} tasks){crowd}, "
        f"{protocol}"
    )
    print("| metric | mean | s.e. | per task seed |\n|---|---|---|---|")
    for k, v in pool.items():
        per = " ".join(f"{x:.2f}" for x in v["per_task_seed"])
        print(f"| {k} | {v['mean']:.2f} | {v['se']:.2f} | {per} |")
    print(failure_line(fails))
    print(f"wrote {p.out / 'results.json' if p.out else ''}")


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
    with one_line_errors(interrupted=None) as failed:
        p = plan(args)  # every check, and the output folder, before the evaluation
    if failed.code is not None:
        return failed.code
    if p.task_seeds is None:
        s = p.setup
        n_seeds = len(s.seed_ids) or 1
        source = "the paper's scenarios" if s.scenarios else f"task seed {s.task_seed}"
        if s.perturbation != "none":
            source += f", crowd perturbed {s.perturbation}"
        print(
            f"[evaluate] {s.label}: {s.env_name}/{s.split} ({source}), "
            f"{len(s.task_ids)} task(s), {n_seeds} seed(s), controller {s.controller}",
            flush=True,
        )
    with one_line_errors(interrupted=None) as failed:  # results.json written before printing
        ev = p.run(_print_task_set)
    if failed.code is not None:
        return failed.code
    if p.task_seeds is not None:
        _print_pooled(p, ev.record)
        return 0
    record = ev.record
    print(f"{record['protocol']}; {record['wall_s']:.1f} s", flush=True)
    print(tables(record))
    print(failure_line(record["failures"]))
    print(f"wrote {ev.written[0]}" + "".join(f", {q.name}" for q in ev.written[1:]))
    return 0
