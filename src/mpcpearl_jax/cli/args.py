"""Building a run's config from a command line, for every registered algorithm
(`mpcpearl_jax.algorithms`): the training commands' options (`parser`, `parse_args`: the task
families' commands for MPC-PEARL, an algorithm's own command from its registration),
`build_config`, `--help-config`, and `config_from_argv`, the config a training command's argv
builds (the lab's campaigns check their runs with it)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from mpcpearl_jax.config import PRESETS, RESULT_NEUTRAL, ExperimentConfig, read_config, resolve
from mpcpearl_jax.errors import ConfigError


def algorithm_of(algorithm: Any = None) -> Any:
    """The registered algorithm `algorithm` names (a name or the object; None: MPC-PEARL)."""
    from mpcpearl_jax import algorithms

    if algorithm is None or isinstance(algorithm, str):
        return algorithms.get(algorithm or algorithms.DEFAULT)
    return algorithm


def add_run_mode_options(p: argparse.ArgumentParser) -> None:
    """--resume or --overwrite (not both): continue the run in --out, or replace it."""
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="continue the run in --out")
    mode.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the run in --out (its records, checkpoints and figures are removed)",
    )


def add_seed_options(p: argparse.ArgumentParser) -> None:
    """--seeds and --seed."""
    p.add_argument("--seeds", type=int, help="independent seeds trained in one program")
    p.add_argument("--seed", type=int, help="base seed (seed s uses seed + s)")


def add_iterations_option(p: argparse.ArgumentParser, algorithm: Any) -> None:
    """--iterations, as `algorithm` trains them."""
    p.add_argument("--iterations", type=int, help=algorithm.iterations_help)


def add_out_options(p: argparse.ArgumentParser, algorithm: Any) -> None:
    """--out (its default: the algorithm's run folder under runs/) and --resume or --overwrite."""
    folder = (algorithm.run_folder or "{label}").format(
        env="<env>", preset="<preset>", label="<label>"
    )
    p.add_argument("--out", type=Path, help=f"run directory (default runs/{folder})")
    add_run_mode_options(p)


def add_progress_option(p: argparse.ArgumentParser, algorithm: Any) -> None:
    """--no-progress: no line per iteration (the algorithm's `progress_line`), or no progress
    bar."""
    if algorithm.progress_line is not None:
        p.add_argument("--no-progress", action="store_true", help="no line per iteration")
        return
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bar (it says 'compiling' during the first iteration, then shows per "
        "iteration the training episodes' mean 'episode return', the share of their steps the "
        "MPC acted ('MPC-acted steps') and, at evaluations, the test tasks' success rate "
        "('test SR') and collision-free rate ('test CFR'); its ETA leaves out the first "
        "iteration)",
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
        above: list[str] = []
        line = node.lineno - 1
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

    from mpcpearl_jax.config import chosen_elsewhere, override_sections

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
            if chosen_elsewhere(sub, f.name):  # --set does not change it
                continue
            default = f.default
            if default is dataclasses.MISSING:
                default = f.default_factory()  # type: ignore[misc,operator]
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
        default=DefaultPreset(default_preset),
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
    add_seed_options(p)
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
    env: str = "restaurant",
    default_preset: str = "default",
    command: str | None = None,
    *,
    algorithm: Any = None,
    description: str | None = None,
) -> argparse.ArgumentParser:
    """The training command's parser for family `env` and `algorithm` (a registered name or
    object; default MPC-PEARL). An algorithm with a command of its own (`Algorithm.command`) gets
    that command's options from its registration (`algorithm_parser`); MPC-PEARL the task
    families' (its task-source options; `command` names the program, default `env`'s own)."""
    algorithm = algorithm_of(algorithm)
    if algorithm.command is not None:
        return algorithm_parser(algorithm, env, description)
    p = argparse.ArgumentParser(
        prog=f"python -m experiments.{command or env}",
        description=description
        or f"Train and evaluate MPC-PEARL (and its baselines) on the {env} tasks: "
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
    add_iterations_option(p, algorithm)
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
    add_out_options(p, algorithm)
    add_progress_option(p, algorithm)
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
        default=COMMAND_DEFAULTS["coordinator_timeout"],
        metavar="S",
        help="seconds to wait for the coordinator and the other processes (default 120)",
    )
    return p


# the task families' command options an algorithm's own command does not offer, at their
# values when not given (the training command reads one namespace)
COMMAND_DEFAULTS: dict[str, Any] = dict(
    config=None,
    label=None,
    eval_minutes=None,
    policy_only=False,
    tensorboard=False,
    debug=False,
    print_config=False,
    coordinator=None,
    num_processes=None,
    process_id=None,
    coordinator_timeout=120.0,
)


def algorithm_parser(
    algorithm: Any, env: str = "restaurant", description: str | None = None
) -> argparse.ArgumentParser:
    """The parser of `algorithm`'s own training command (`python -m experiments.COMMAND`), from
    its registration: --env one of its families (default `env`), --preset one of its presets,
    --iterations, --minutes (stopping the iterations early), the seeds, the task source, --set
    over its config's sections, --out (default its run folder), --resume or --overwrite,
    --no-progress. `description` is the help's text, as written."""
    from mpcpearl_jax.config import override_sections

    p = argparse.ArgumentParser(
        prog=f"python -m experiments.{algorithm.command}",
        description=description,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--env", default=DefaultPreset(env), choices=algorithm.families)
    p.add_argument("--preset", default=DefaultPreset("default"), choices=sorted(algorithm.presets))
    add_iterations_option(p, algorithm)
    p.add_argument(
        "--minutes",
        type=float,
        help="stop training after this many minutes (checkpointed; --resume continues)",
    )
    add_seed_options(p)
    add_task_source_options(p, hold_out_val=True)
    sections = [f"{s}.FIELD" for s in override_sections(algorithm.config_type) if s]
    sections.append("a top-level field")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help=f"override a field: {', '.join(sections[:-1])} or {sections[-1]} (JSON values)",
    )
    add_out_options(p, algorithm)
    add_progress_option(p, algorithm)
    p.set_defaults(**COMMAND_DEFAULTS)
    return p


def build_config(args: argparse.Namespace, env: str, *, algorithm: Any = None, **extra) -> Any:
    """The config of the command line `args` for family `env` and `algorithm` (a registered name
    or object; default MPC-PEARL), through `mpcpearl_jax.config.resolve` with the algorithm's
    config type: --preset or --config, or with --resume --out RUN the run's own config (where
    the command line names no preset: `_resumed_run`); the task source, then --eps,
    --iterations, --seeds, --seed, --devices, --algo and `extra` (top-level fields; `mpc`: a
    dict of MPCConfig fields), then --set; checked across fields (`validate`, which `resolve`
    runs)."""
    algorithm = algorithm_of(algorithm)
    if getattr(args, "data", None) is not None and env == "restaurant":
        raise ConfigError("--data: only the sidewalk env reads a data file")
    base: Any = args.preset
    run = _resumed_run(args, env, algorithm)
    if run is not None and not _names_env(args):  # the family of the run
        args.env = env = run.env
    if run is not None and isinstance(args.preset, DefaultPreset):  # the run's own config
        preset = recorded_preset(run, algorithm).split()[0]
        base, args.preset = run, DefaultPreset(preset)
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
        ("train.eps", getattr(args, "eps", None)),
        (algorithm.iterations_field, getattr(args, "iterations", None)),
        ("seeds", args.seeds),
        ("seed", args.seed),
        ("devices", getattr(args, "devices", None)),
        ("pearl.use_context", False if getattr(args, "algo", None) == "sac" else None),
    )
    changes.update({key: value for key, value in options if value is not None})
    cfg = resolve(
        base,
        env,
        config_type=algorithm.config_type,
        changes=changes,
        overrides=args.set,
        scenarios=getattr(args, "scenarios", None),
        hold_out_val=getattr(args, "hold_out_val", False),
        data=getattr(args, "data", None),
    )
    if run is not None and base is not run:
        _check_same_run(run, cfg, args, algorithm)
    return cfg


class DefaultPreset(str):
    """An option's value when the command line gives none (a str equal to the default): --preset
    (then --resume continues from the run's own config instead), and the --env of an
    algorithm's own command (then --resume continues on the run's family)."""


def _names_env(args: argparse.Namespace) -> bool:
    """Whether the command line names the task family (the task families' commands always do)."""
    return not isinstance(getattr(args, "env", None), DefaultPreset)


def _resumed_run(args: argparse.Namespace, env: str, algorithm: Any) -> Any:
    """With --resume --out RUN (and no --config): RUN's recorded config, which the resume
    continues from, where it is `algorithm`'s and of family `env` (any family where the command
    line names none); None otherwise, or where it cannot be read (opening the run names the
    problem)."""
    from mpcpearl_jax.errors import CheckpointError

    out = getattr(args, "out", None)
    if not getattr(args, "resume", False) or out is None or getattr(args, "config", None):
        return None
    try:
        run = algorithm.kind.load_config(Path(out), True)
    except (ConfigError, CheckpointError, OSError):
        return None
    return run if run.env == env or not _names_env(args) else None


def recorded_preset(cfg: Any, algorithm: Any = None) -> str:
    """The preset a run's config was built from: the one of its algorithm's presets whose config
    differs from it in the fewest fields (the per-run options --iterations, --eps, --seeds,
    --seed, --algo, --devices and the task source left out), as 'NAME', or 'NAME plus N changed
    field(s)'."""
    from mpcpearl_jax import algorithms
    from mpcpearl_jax.training.checkpoint import config_differences

    algorithm = algorithm or algorithms.of_config(cfg) or algorithm_of()
    ignore: tuple[str, ...] = (algorithm.iterations_field, "train.eps", "seeds", "seed")
    ignore += (*RESULT_NEUTRAL, "pearl.use_context", "scenarios", "hold_out_val", "data")
    ignore += ("env_overrides",)
    counts: dict[str, int] = {}
    for name in sorted(algorithm.presets):
        try:
            preset = resolve(name, cfg.env, config_type=algorithm.config_type)
            counts[name] = len(config_differences(cfg, preset, ignore=ignore))
        except (ConfigError, ValueError, TypeError):
            continue
    if not counts:
        return "unknown"
    best = min(counts, key=lambda n: (counts[n], n != "default"))
    return best if counts[best] == 0 else f"{best} plus {counts[best]} changed field(s)"


def _check_same_run(run: Any, cfg: Any, args: argparse.Namespace, algorithm: Any) -> None:
    """--resume with another --preset than the run's, giving another config: ConfigError naming
    the run's preset and the fields, and the resume that reads the run's own config (with the
    run's own preset, the session's check names the differing fields)."""
    from mpcpearl_jax.training.checkpoint import config_differences

    diff = config_differences(run, cfg, ignore=(algorithm.iterations_field, *RESULT_NEUTRAL))
    started = recorded_preset(run, algorithm)
    if not diff or started.split()[0] == args.preset:  # the session lists the fields
        return
    shown = ", ".join(diff[:4]) + (f" and {len(diff) - 4} more" if len(diff) > 4 else "")
    raise ConfigError(
        f"{args.out}: the run was started from preset {started}; --preset "
        f"{args.preset} and the other options give another config ({shown}); continue it with "
        f"--resume --out {args.out} alone (it reads the run's own config), or choose another --out"
    )


def parse_args(
    env: str,
    argv: list[str] | None = None,
    *,
    command: str | None = None,
    from_config=False,
    algorithm: Any = None,
    description: str | None = None,
) -> argparse.Namespace:
    """The training command's arguments (`parser`; `argv` kept as `args.argv`). `--env
    restaurant` or `--env sidewalk` picks that family's task-source options (--scenarios, --data)
    whatever the command; with `from_config`, so does the family a `--config` file records when
    no --env is given. An algorithm's own command offers both."""
    argv = list(sys.argv[1:] if argv is None else argv)
    algorithm = algorithm_of(algorithm)
    if algorithm.command is not None:
        args = parser(env, algorithm=algorithm, description=description).parse_args(argv)
        args.argv = argv
        return args
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--env")
    pre.add_argument("--config", type=Path)
    known = pre.parse_known_args(argv)[0]
    family = known.env or (_recorded_env(known.config) if from_config else None)
    options = family if family in ("restaurant", "sidewalk") else env
    args = parser(options, command=command or env, description=description).parse_args(argv)
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


def budget_error(args: argparse.Namespace, learning_curve: bool = True) -> str | None:
    """The one-line error of a wrong combination of the budget options, or None. Without a
    `learning_curve`, --minutes only stops the iterations early: it must be positive."""
    if args.minutes is None:
        given = (("--eval-minutes", args.eval_minutes), ("--policy-only", args.policy_only))
        for flag, value in given:
            if value:
                return f"{flag} applies to a time budget: give --minutes too"
        return None
    if not (args.minutes > 0 and math.isfinite(args.minutes)):
        return f"--minutes must be positive, got {args.minutes}"
    if not learning_curve:
        return None
    if args.eval_minutes is not None and not args.eval_minutes > 0:
        return f"--eval-minutes must be positive, got {args.eval_minutes}"
    if args.iterations is not None:
        return "--minutes and --iterations: give one (a budget of time, or of iterations)"
    if args.resume and args.policy_only:
        return "--resume continues a run: not with --policy-only (no checkpoint)"
    return None


def env_family(spec: str, error: type[Exception] = ValueError) -> str:
    """--env's family: NAME or MODULE:NAME (`envs.load_family`, which imports MODULE to register
    NAME); its error as `error`, naming the flag."""
    from mpcpearl_jax.envs import load_family

    try:
        return load_family(spec)
    except ValueError as e:
        raise error(f"--env {e}") from None


def config_from_argv(command: str, argv: list[str]):
    """The config the training command `command` (restaurant, sidewalk, learning, or an
    algorithm's own: grbal) builds from `argv`, as that command would (argparse's SystemExit on
    a command line it refuses, its message printed)."""
    from mpcpearl_jax import algorithms

    own = [algorithms.get(n) for n in algorithms.names() if algorithms.get(n).command == command]
    if own:
        args = parse_args("restaurant", argv, algorithm=own[0])
        return build_config(args, env_family(args.env), algorithm=own[0])
    if command == "learning":
        args = parse_args("restaurant", argv, command="learning", from_config=True)
        return build_config(args, env_family(args.env))
    return build_config(parser(command).parse_args(argv), command)
