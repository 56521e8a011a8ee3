"""Command-line interface shared by the experiment entry points."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from mpcpearl_jax.config import PRESETS, ExperimentConfig, read_config, resolve
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.evaluation.report import run_label
from mpcpearl_jax.training.budget import default_label
from mpcpearl_jax.cli.stopping import (  # noqa: F401  (the commands' names for them)
    exit_interrupted,
    stop_exit_code,
    stoppable,
    stops_with,
)


def add_run_mode_options(p: argparse.ArgumentParser) -> None:
    """--resume or --overwrite (not both): continue the run in --out, or replace it."""
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="continue the run in --out")
    mode.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the run in --out (its records, checkpoints and figures are removed)",
    )


def add_task_source_options(
    p: argparse.ArgumentParser,
    env: str | None = None,
    *,
    hold_out_val: bool = False,
    from_run: bool = False,
) -> None:
    """--scenarios (restaurant: the paper's own tasks) and --data (sidewalk: a trajectory file),
    where a command's tasks come from: only the family's own option when `env` is given, both
    when the command picks the family (--env, a run). `hold_out_val` adds --hold-out-val
    (training); `from_run`: the default is the evaluated run's task source."""
    default = "the run's" if from_run else None
    if env in (None, "restaurant"):
        p.add_argument(
            "--scenarios",
            type=Path,
            metavar="DIR",
            help="restaurant: the paper's own scenarios (a clone of the authors' repository or "
            "a folder with scenarios/X.npy and optionally scenarios_out_of_distribution/X.npy) "
            "instead of the generated crowds; splits train 0-179, val 150-179, test 180-204, "
            f"ood the 25 shifted ones (default: {default or 'the generated crowds'})",
        )
        if hold_out_val:
            p.add_argument(
                "--hold-out-val",
                action="store_true",
                help="--scenarios: train on tasks 0-149 only, keeping 150-179 as the val split",
            )
    if env in (None, "sidewalk"):
        p.add_argument(
            "--data",
            type=Path,
            help="sidewalk: an ETH/UCY trajectory file (e.g. UCY crowds_zara01.txt; default: "
            f"{default or 'the built-in synthetic crowd'})",
        )


class _RunConfigAction(argparse.Action):
    """--config FILE: the file, and the run's folder name as the name runs are labelled with
    in place of a preset's."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        path = Path(values)
        setattr(namespace, self.dest, path)
        namespace.preset = path.parent.name if path.name == "config.json" else path.name


def field_comments(cls: type) -> dict[str, tuple[str, str]]:
    """{field: (heading, comment)} from the source of the dataclass `cls`: a field's comment is
    the one on its own line, else the comment lines right above it; a `# ---- ...` line (through
    the first line that ends with ')') is a heading, given with the field it precedes."""
    import ast
    import inspect
    import io
    import textwrap
    import tokenize

    src = textwrap.dedent(inspect.getsource(cls))
    comments: dict[int, tuple[str, bool]] = {}  # line -> (text, whole line)
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = (tok.string[1:].strip(), tok.line.lstrip().startswith("#"))
    out: dict[str, tuple[str, str]] = {}
    for node in ast.parse(src).body[0].body:  # type: ignore[attr-defined]
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        above, line = [], node.lineno - 1
        while line in comments and comments[line][1]:
            above.insert(0, comments[line][0])
            line -= 1
        heading: list[str] = []
        if above and above[0].startswith("----"):
            end = next((i for i, t in enumerate(above) if t.endswith(")")), 0)
            heading, above = above[: end + 1], above[end + 1 :]
            heading[0] = heading[0].lstrip("- ")
        own = comments.get(node.end_lineno or node.lineno)
        text = own[0] if own and not own[1] else " ".join(above)
        out[node.target.id] = (" ".join(heading), text)
    return out


def config_help(cls: type = ExperimentConfig, width: int = 100) -> str:
    """Every field --set can change in a run config `cls`, section by section, with its default
    (the dataclass's) and the comment its source gives it (`field_comments`)."""
    import dataclasses
    import textwrap

    from mpcpearl_jax.config import override_sections

    lines = [
        "Every config field, changed with --set SECTION.FIELD=VALUE (JSON values). The defaults "
        "are the dataclasses' (the paper's settings); a preset and the task family change some: "
        "--print-config shows a run's resolved config.",
    ]
    sections = override_sections(cls)
    for section, sub in sections.items():
        doc = (sub.__doc__ or "").strip().splitlines()[0]
        lines += ["", f"{section or 'top level'} ({sub.__name__}: {doc})"]
        notes = field_comments(sub)
        nested = {sections[k].__name__ for k in sections if k}  # the sections listed apart
        for f in dataclasses.fields(sub):
            kind = getattr(f.type, "__name__", f.type)  # a name under `from __future__`
            if kind in nested or f.name == "env_overrides" or not f.init:
                continue
            default = f.default
            if default is dataclasses.MISSING:
                default = f.default_factory()  # type: ignore[misc]
            heading, text = notes.get(f.name, ("", ""))
            if heading:
                lines += textwrap.wrap(f"-- {heading}", width, initial_indent="  ")
            name = f"{section}.{f.name}" if section else f.name
            lines += textwrap.wrap(
                f"{name} = {default!r}" + (f": {text}" if text else ""),
                width,
                initial_indent="  ",
                subsequent_indent="      ",
            )
    return "\n".join(lines)


class _HelpConfigAction(argparse.Action):
    """--help-config: print `config_help()` and exit."""

    def __init__(self, option_strings, dest, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(config_help())
        parser.exit()


def add_config_options(
    p: argparse.ArgumentParser, env: str, default_preset: str = "default"
) -> None:
    """The options `build_config` reads: --preset or --config, --eps, --seeds, --seed, --algo,
    --set (and --scenarios, --hold-out-val for the restaurant, --data for the sidewalk). Shared
    with `experiments.learning`."""
    base = p.add_mutually_exclusive_group()
    base.add_argument(
        "--preset",
        default=default_preset,
        metavar="{" + ",".join(sorted(PRESETS)) + "}",
        help="smoke: ~2 min pipeline check; default: 4-5 minutes of training on a quiet 2-core "
        "CPU; recipe: the recommended CPU recipe, trained on a time budget (--minutes 24); "
        "cpu-explore: the recipe without automatic entropy tuning; paper: method §7 exactly "
        "(docs/usage.md)",
    )
    base.add_argument(
        "--config",
        action=_RunConfigAction,
        metavar="RUN/config.json",
        help="start from a run's recorded config instead of a preset (the other options apply "
        "on top; the run is named after RUN's folder where a preset's name would go)",
    )
    p.add_argument("--eps", type=float, help="MPC probability on an event (0 = PEARL)")
    p.add_argument("--seeds", type=int, help="independent seeds trained in one program")
    p.add_argument("--seed", type=int, help="base seed (seed s uses seed + s)")
    p.add_argument(
        "--devices",
        type=int,
        help="devices the seeds are split over (default: every device the seed count divides "
        "evenly into; per-seed results do not depend on it)",
    )
    p.add_argument(
        "--algo",
        choices=("pearl", "sac"),
        default="pearl",
        help="sac = no context encoder (the paper's MPC-SAC baseline)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="override any config field, e.g. --set train.updates_per_iteration=200 "
        "--set pearl.hidden=[256,256] --set mpc.v_max=4 (JSON values; booleans true/false, "
        "True/False or 1/0)",
    )
    p.add_argument(
        "--debug", action="store_true", help="show the traceback of an error, not one line"
    )
    p.add_argument(
        "--print-config",
        action="store_true",
        help="print the resolved config (JSON, as config.json records it) and exit",
    )
    p.add_argument(
        "--help-config",
        action=_HelpConfigAction,
        help="list every config field --set can change, with its default and meaning, and exit",
    )
    add_task_source_options(p, env, hold_out_val=True)


def parser(
    env: str, default_preset: str = "default", command: str | None = None
) -> argparse.ArgumentParser:
    """The training command's parser for family `env` (its task-source options); `command`
    names the program (default `env`'s own)."""
    p = argparse.ArgumentParser(
        prog=f"python -m experiments.{command or env}",
        description=f"Train and evaluate MPC-PEARL (and its baselines) on the {env} tasks: "
        "--iterations N (the preset's by default), or --minutes M of training with a learning "
        "curve.",
    )
    add_config_options(p, env, default_preset)
    p.add_argument(
        "--env",
        default=env,
        metavar="FAMILY",
        help=f"the task family: a registered one (restaurant, sidewalk; default {env}) or "
        "MODULE:NAME, a module that registers NAME when imported, e.g. examples.corridor:corridor "
        "(docs/custom_tasks.md)",
    )
    p.add_argument("--iterations", type=int, help="meta-training iterations")
    budget = p.add_argument_group(
        "a time budget and its learning curve (instead of --iterations; writes curve.json, "
        "curve.png and a time-to-target table)"
    )
    budget.add_argument(
        "--minutes",
        type=float,
        help="train for M minutes (from the start of the first iteration, compilation "
        "included, evaluation excluded)",
    )
    budget.add_argument(
        "--eval-minutes",
        type=float,
        help="minutes of training between the curve's evaluations (default: --minutes / 8; at "
        "most --minutes / 2); there is always one at minute 0 and one at the end",
    )
    budget.add_argument(
        "--policy-only",
        action="store_true",
        help="save policy.msgpack only, not the orbax checkpoint of the whole training state "
        "(replay buffers: hundreds of MB for the larger presets; needed only for --resume)",
    )
    p.add_argument(
        "--label",
        help="the run's name (default <env>-<preset>-<algo>-eps<eps>): the folder under runs/ "
        "when --out is not given, and the name on the curve",
    )
    p.add_argument("--out", type=Path, help="run directory (default runs/<label>)")
    add_run_mode_options(p)
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bar (it says 'compiling' during the first iteration, then shows per "
        "iteration the training episodes' mean 'episode return', the share of their steps the "
        "MPC acted ('MPC-acted steps') and, at evaluations, the test tasks' success rate "
        "('test SR') and collision-free rate ('test CFR'); its ETA leaves out the first "
        "iteration)",
    )
    p.add_argument(
        "--tensorboard",
        action="store_true",
        help="also log the metrics to <out>/tensorboard (watch with tensorboard --logdir runs)",
    )
    g = p.add_argument_group(
        "several processes or hosts (jax.distributed; all three, the same command on each)"
    )
    g.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0")
    g.add_argument("--num-processes", type=int, metavar="N", help="number of processes")
    g.add_argument("--process-id", type=int, metavar="I", help="this process, 0 to N - 1")
    g.add_argument(
        "--coordinator-timeout",
        type=float,
        default=120.0,
        metavar="S",
        help="seconds to wait for the coordinator and the other processes (default 120)",
    )
    return p


def build_config(args: argparse.Namespace, env: str, **extra) -> ExperimentConfig:
    """The config of the command line `args` for family `env` (`mpcpearl_jax.config.resolve`):
    --preset or --config, the task source, then --eps, --iterations, --seeds, --seed,
    --devices, --algo and `extra` (top-level fields; `mpc`: a dict of MPCConfig fields), then
    --set; checked across fields (`validate`, which `resolve` runs)."""
    base: str | ExperimentConfig = args.preset
    if getattr(args, "config", None) is not None:
        base = read_config(args.config)
        if base.env != env:
            raise ConfigError(
                f"--config {args.config}: a {base.env} run, not {env} (train it with the "
                f"{base.env} command)"
            )
    changes = {f"mpc.{k}": v for k, v in extra.pop("mpc", {}).items()}
    changes.update(extra)
    options = (
        ("train.eps", args.eps),
        ("train.iterations", getattr(args, "iterations", None)),
        ("seeds", args.seeds),
        ("seed", args.seed),
        ("devices", getattr(args, "devices", None)),
        ("pearl.use_context", False if args.algo == "sac" else None),
    )
    changes.update({key: value for key, value in options if value is not None})
    return resolve(
        base,
        env,
        changes=changes,
        overrides=args.set,
        scenarios=getattr(args, "scenarios", None),
        hold_out_val=getattr(args, "hold_out_val", False),
        data=getattr(args, "data", None),
    )


def error_line(e: BaseException) -> str:
    """One line for a command-line error: OSErrors name their file, others carry their own."""
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or type(e).__name__}"
    if isinstance(e, UnicodeDecodeError):
        return f"not a text file ({e.reason} at byte {e.start})"
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


def parse_args(
    env: str, argv: list[str] | None = None, *, command: str | None = None, from_config=False
) -> argparse.Namespace:
    """The training command's arguments. `--env restaurant` or `--env sidewalk` picks that
    family's task-source options (--scenarios, --data) whatever the command; with `from_config`,
    so does the family a `--config` file records when no --env is given."""
    argv = list(sys.argv[1:] if argv is None else argv)
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--env")
    pre.add_argument("--config", type=Path)
    known = pre.parse_known_args(argv)[0]
    family = known.env or (_recorded_env(known.config) if from_config else None)
    options = family if family in ("restaurant", "sidewalk") else env
    args = parser(options, command=command or env).parse_args(argv)
    if known.env is None and options != env:
        args.env = options
    args.argv = argv
    return args


def _recorded_env(config: Path | None) -> str | None:
    """The family a --config file records (None when unreadable: building the config names the
    problem)."""
    import json

    try:
        return json.loads(Path(config).read_text()).get("env") if config else None
    except (OSError, ValueError, AttributeError):
        return None


def _budget_error(args: argparse.Namespace) -> str | None:
    """The one-line error of a wrong combination of the budget options, or None."""
    if args.minutes is None:
        given = (("--eval-minutes", args.eval_minutes), ("--policy-only", args.policy_only))
        for flag, value in given:
            if value:
                return f"{flag} applies to a time budget: give --minutes too"
        return None
    if not (args.minutes > 0 and math.isfinite(args.minutes)):
        return f"--minutes must be positive, got {args.minutes}"
    if args.eval_minutes is not None and not args.eval_minutes > 0:
        return f"--eval-minutes must be positive, got {args.eval_minutes}"
    if args.iterations is not None:
        return "--minutes and --iterations: give one (a budget of time, or of iterations)"
    if args.resume and args.policy_only:
        return "--resume continues a run: not with --policy-only (no checkpoint)"
    return None


@stoppable
def main(
    env: str,
    argv: list[str] | None = None,
    *,
    command: str | None = None,
    from_config: bool = False,
    clock=time.perf_counter,
    **extra,
) -> int:
    """Exit codes: 0 done, 2 a command-line error (config, data, checkpoint, permissions: one
    line on stderr, the traceback with --debug), 1 training diverged, 130 Ctrl-C (resumable).
    `clock` times a --minutes budget (tests give a fake one)."""
    args = parse_args(env, argv, command=command, from_config=from_config)
    from mpcpearl_jax.training.run import open_session

    def fail(e: BaseException, code: int = 2) -> int:
        return fail_line(e, code, args.debug)

    if _budget_error(args):
        return fail(ValueError(_budget_error(args)))
    if args.tensorboard:
        from mpcpearl_jax.training.livelog import LiveLogError, missing

        if missing():
            return fail(LiveLogError(missing()))
    if args.print_config:
        try:
            cfg = build_config(args, env_family(args.env), **extra)
        except (ValueError, TypeError, OSError) as e:
            return fail(e)
        print(cfg.to_json(), flush=True)
        return 0
    budget = args.minutes is not None
    t_wall0 = time.perf_counter()
    try:  # everything up to training: each check names the field, file or folder
        with one_line_errors(args.debug, interrupted=None) as startup:
            _initialize(args)  # before any JAX work
            family = env_family(args.env)
            cfg = build_config(args, family, **extra)
            label = args.label or default_label(family, args.preset, args.algo, cfg.train.eps)
            out = args.out or Path("runs") / label
            finished = finished_line(out, cfg, args.minutes) if args.resume else None
            if finished is not None:  # nothing to train or evaluate: no file is touched
                print(finished, flush=True)
                return 0
            _print_start(args, family, cfg, label, out)
            load_start = None
            if budget:
                from mpcpearl_jax.training.budget import load_at_start

                load_start = load_at_start()
            t_wall0 = time.perf_counter()
            sess = open_session(
                cfg,
                out,
                resume=args.resume,
                until_budget=budget,
                tensorboard=args.tensorboard,
                overwrite=args.overwrite,
            )
    except KeyboardInterrupt:  # the session closed what it had opened
        exit_interrupted("interrupted before training started")
    if startup.code is not None:
        return startup.code
    with sess:  # the run folder stays locked until its last file is written
        if budget:
            from mpcpearl_jax.training.budget import warn_if_busy

            warn_if_busy(load_start)  # measured before the trainer was built
        return _train(args, sess, label, load_start, t_wall0, clock)


def finished_line(out: Path, cfg: ExperimentConfig, minutes: float | None = None) -> str | None:
    """For --resume: the one line that says the run in `out` is finished, or None where there
    is something to train or evaluate. On iterations: results.json written for the config's
    iterations, every one of them logged; on a time budget (`minutes`): results.json written
    and curve.json's budget spent, and `minutes` no larger than it."""
    import json

    from mpcpearl_jax.runfolder import LOG_FILE, read_log
    from mpcpearl_jax.training.budget import CURVE_FILE

    try:
        done = json.loads((out / "results.json").read_text())["config"]["train"]["iterations"]
        logged = len(read_log(out / LOG_FILE))
        curve = json.loads((out / CURVE_FILE).read_text()) if minutes is not None else {}
    except (OSError, ValueError, KeyError, TypeError):
        return None  # opening the session names any problem
    if minutes is not None:
        budget = curve.get("budget_minutes")
        spent = curve.get("stopped") == "budget" and curve.get("iterations") == logged
        if not (spent and isinstance(budget, (int, float)) and minutes <= budget):
            return None
        return (
            f"{out}: finished ({budget:g} minutes of training, results.json written); nothing "
            f"to do (to train it further: --resume --minutes M, M above {budget:g})"
        )
    if done != cfg.train.iterations or logged != done:
        return None
    return (
        f"{out}: finished ({done} iteration(s), results.json written); nothing to do (to train it "
        f"further: --resume --iterations N, N above {done})"
    )


def _initialize(args: argparse.Namespace) -> None:
    """jax.distributed for --coordinator and its options (nothing without them)."""
    from mpcpearl_jax.distributed import CoordinatorTimeout, initialize

    try:
        initialize(args.coordinator, args.num_processes, args.process_id, args.coordinator_timeout)
    except CoordinatorTimeout as e:  # the runtime's start-up thread would abort the process
        print(f"error: {e}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(2)


def _print_start(args: argparse.Namespace, family: str, cfg, label: str, out: Path) -> None:
    """The command's first line: what it trains, how long, into which folder."""
    if args.minutes is not None:
        from mpcpearl_jax.training.budget import eval_every_minutes

        every = eval_every_minutes(args.minutes, args.eval_minutes)
        print(
            f"[{family}] {run_label(cfg)} {label}: preset={args.preset} seeds={cfg.seeds} "
            f"budget={args.minutes:g} min, eval every {every:.3g} min "
            f"({'online' if cfg.online_eval else 'adaptation'} protocol), out={out}"
            + (" (resumed)" if args.resume else ""),
            flush=True,
        )
        return
    print(
        f"[{family}] {run_label(cfg)} preset={args.preset} seeds={cfg.seeds} "
        f"iterations={cfg.train.iterations} out={out}",
        flush=True,
    )
    if args.preset == "default" and args.config is None and args.iterations is None:
        print(DEFAULT_NOTE, flush=True)  # its figures are for the preset's 75 iterations


def _train(args: argparse.Namespace, sess, label: str, load_start, t_wall0: float, clock) -> int:
    """The training command's one path: train the open session in the iterations or the minutes
    mode, `training.final.finish` (results.json, figures, a minutes run's curve), then print what
    happened; its errors as one line (`one_line_errors`)."""
    with one_line_errors(args.debug) as outcome:
        return _train_and_report(args, sess, label, load_start, t_wall0, clock)
    return outcome.code


def _train_and_report(args, sess, label, load_start, t_wall0, clock) -> int:
    from mpcpearl_jax.distributed import is_primary
    from mpcpearl_jax.evaluation.report import results_table
    from mpcpearl_jax.training.final import finish
    from mpcpearl_jax.training.run import RunInterrupted

    cfg, out, start, minutes = sess.cfg, sess.run_dir, sess.done, args.minutes
    build_s = time.perf_counter() - t_wall0  # the trainer and its initial (or restored) state
    t0 = time.perf_counter()
    if minutes is None:
        state, info = _train_iterations(sess, progress=not args.no_progress)
    else:
        from mpcpearl_jax.training.budget import train_minutes

        state, info = train_minutes(
            sess,
            minutes=minutes,
            eval_minutes=args.eval_minutes,
            policy_only=args.policy_only,
            on_point=print_point,
            clock=clock,
        )
    train_s = time.perf_counter() - t0
    stopped = info["stopped"]
    if stopped.startswith("diverged"):
        if minutes is None:
            raise info["error"]
        print(f"error: {info['error']}", file=sys.stderr, flush=True)  # the curve is still written
    if minutes is None:
        if stopped == "done":
            print(f"trained in {train_s:.1f} s; evaluating", flush=True)
        try:
            results = finish(sess, state, info, label=run_label(cfg))
        except KeyboardInterrupt:
            print(
                f"interrupted in the final evaluation; training is saved (iteration "
                f"{cfg.train.iterations}): evaluate it with --resume",
                file=sys.stderr,
                flush=True,
            )
            return stop_exit_code()
    else:
        curve = dict(preset=args.preset, argv=args.argv, resumed=args.resume)
        curve.update(load_start=load_start, build_s=build_s, t_wall0=t_wall0)
        results = finish(sess, state, info, label=label, **curve)
    if stopped == "interrupted":
        line = str(RunInterrupted(info["iterations"], info["lost"]))
        if args.policy_only:
            saved = info["iterations"]
            line = f"interrupted at iteration {saved} (--policy-only: no checkpoint to resume from)"
        print(line, file=sys.stderr, flush=True)
        return stop_exit_code()
    if results is not None and is_primary():
        print(results_table(results))
    if minutes is not None:
        return _curve_summary(info, label, out)
    print(trained_line(cfg, train_s, start), flush=True)
    print(LONGER if cfg.env == "restaurant" else LONGER_ANY, flush=True)
    print(f"results, curves and figures in {out}", flush=True)
    return 0


def _train_iterations(sess, progress: bool):
    """`training.run.train_iterations` with the command's stop signals and progress bar."""
    from mpcpearl_jax.training.run import progress_bar, train_iterations

    bar = progress_bar(sess) if progress else None
    try:
        return train_iterations(sess, bar.row if bar is not None else None, handle_sigint=True)
    finally:
        if bar is not None:
            bar.close()


def print_point(p: dict) -> None:
    """One line per eval point of a minutes run."""
    print(
        f"[learning] {p['minutes']:7.2f} min  it {p['iteration']:6d}  grad {p['grad_steps']:8d}"
        f"  test SR {p['test_SR']:.2f} CFR {p['test_CFR']:.2f} ret {p['test_return']:8.1f}"
        f"  val SR {p['val_SR']:.2f} CFR {p['val_CFR']:.2f}  (eval {p['eval_s']:.1f} s)",
        flush=True,
    )


def _curve_summary(info: dict, label: str, out: Path) -> int:
    """A minutes run's end: the time-to-target table and one line of what it trained; exit 0
    when the budget was spent, 1 when training diverged or no iteration finished."""
    from mpcpearl_jax.training.budget import CURVE_FILE, summary_rows
    from mpcpearl_jax.training.machine import print_table

    record, done = info["curve"], info["iterations"]
    if done == 0:
        print(f"error: no iteration finished; {out / CURVE_FILE} written", file=sys.stderr)
        return 1
    print_table(
        summary_rows(record),
        ["split", "target", "minutes", "grad steps", "iteration"],
        title=f"{label}: time to target (training minutes, compile included)",
    )
    hit = record["time_to"]["train"]["first_success"]
    first = "never" if hit is None else f"{hit['minutes']:.2f} min"
    last, tm = info["points"][-1], record["timing"]
    print(
        f"trained {info['train_s'] / 60:.2f} min ({done} iterations, {record['grad_steps']} "
        f"gradient steps, {record['env_steps']} env steps per seed; first iteration incl. "
        f"compile {info['first_iteration_s']:.1f} s); evaluation {info['eval_s']:.1f} s off the "
        f"clock; first training success: {first}; final test SR {last['test_SR']:.2f}, val SR "
        f"{last['val_SR']:.2f}; total wall {tm['total_wall_s']:.1f} s",
        flush=True,
    )
    print(f"curve, policy and results in {out}", flush=True)
    return 0 if info["stopped"] == "budget" else 1


class Outcome:
    """What `one_line_errors` leaves: the exit code of the error it reported (None: none)."""

    code: int | None = None


@contextlib.contextmanager
def one_line_errors(
    debug: bool = False, interrupted: str | None = "interrupted; continue with --resume"
) -> Iterator[Outcome]:
    """The commands' one error ladder, around their work: each error as one line on stderr
    (`error_line`; the traceback with `debug`) and its exit code in the yielded `Outcome`: 2 a
    config, data, checkpoint or run-folder error, an OS error (a file, permissions, a full disk)
    or XLA's out-of-memory error; 1 training diverged; `stop_exit_code()` a stop signal during
    training (`RunInterrupted`: its line), or a second one (KeyboardInterrupt: `interrupted`;
    None lets it through to the caller)."""
    from mpcpearl_jax.errors import CheckpointError, RunDirError, TrainingDiverged
    from mpcpearl_jax.training.run import RunInterrupted

    outcome = Outcome()
    try:
        yield outcome
    except RunInterrupted as e:  # the last finished iteration saved
        print(str(e), file=sys.stderr, flush=True)
        outcome.code = stop_exit_code()
    except KeyboardInterrupt:  # a second Ctrl-C: stopped at once, the last checkpoint stands
        if interrupted is None:
            raise
        print(interrupted, file=sys.stderr, flush=True)
        outcome.code = stop_exit_code()
    except TrainingDiverged as e:
        outcome.code = fail_line(e, 1, debug)
    except (ValueError, TypeError, OSError, CheckpointError, RunDirError) as e:
        outcome.code = fail_line(e, 2, debug)
    except RuntimeError as e:
        if not out_of_memory(e):
            raise
        outcome.code = fail_line(MemoryError(out_of_memory(e)), 2, debug)


def fail_line(e: BaseException, code: int = 2, debug: bool = False) -> int:
    """Print `e` as one line on stderr (`error_line`) and return `code`; with `debug`, raise it
    (its traceback)."""
    if debug:
        raise e
    print(f"error: {error_line(e)}", file=sys.stderr, flush=True)
    return code


DEFAULT_NOTE = (
    "the default preset: a first look, 75 iterations, about 4-5 minutes of training on a quiet "
    "2-core CPU, up to about 8 on a slower or busy one (the README gives the range over ten "
    "seeds); the "
    "first iteration compiles, up to a minute of it. Far shorter than the paper's training "
    "(printed under the results table)"
)


def env_family(spec: str, error: type[Exception] = ValueError) -> str:
    """--env's family: NAME or MODULE:NAME (`envs.load_family`, which imports MODULE to register
    NAME); its error as `error`, naming the flag."""
    from mpcpearl_jax.envs import load_family

    try:
        return load_family(spec)
    except ValueError as e:
        raise error(f"--env {e}") from None


def out_of_memory(e: BaseException) -> str:
    """The one line of XLA's out-of-memory error ('' for any other error)."""
    text = str(e)
    if "RESOURCE_EXHAUSTED" not in text or "memory" not in text.lower():
        return ""
    first = text.strip().splitlines()[0]
    return f"out of memory ({first}); lower the config's size fields (--set)"


# the recipe of the five-seed comparison (docs/usage.md, "Training longer")
LONGER = (
    "to train longer (docs/usage.md, 'Training longer'): python -m experiments.restaurant "
    "--preset recipe --eps 0.2 --minutes 24"
)
LONGER_ANY = "to train longer: --iterations N, or another preset (docs/usage.md#training-longer)"


def trained_line(cfg: ExperimentConfig, seconds: float, start: int = 0) -> str:
    """What this process trained, for how long and on what (printed under the results table,
    whose paper columns say how long the paper trained)."""
    import jax

    iters = cfg.train.iterations - start
    steps = iters * cfg.train.updates_per_iteration
    dev = jax.devices()[0]
    where = (
        f"a {os.cpu_count()}-core CPU"
        if dev.platform == "cpu"
        else f"{jax.device_count()} x {dev.device_kind}"
    )
    return (
        f"this run: {run_label(cfg)}, {iters} iteration(s) x {cfg.train.updates_per_iteration} "
        f"gradient steps ({steps:,}), {cfg.seeds} seed(s), trained in {seconds / 60:.1f} min on "
        f"{where}"
    )
