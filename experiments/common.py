"""Command-line interface shared by the experiment entry points."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from mpcpearl_jax.config import PRESETS, ExperimentConfig, read_config, resolve
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.evaluation.report import run_label
from mpcpearl_jax.training.stopping import stop_exit_code, stoppable


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
        choices=sorted(PRESETS),
        help="smoke: ~2 min pipeline check; default: 4-5 minutes of training on a quiet 2-core "
        "CPU; "
        "cpu-explore: the recommended CPU recipe; cpu-paper: the paper's algorithm on the CPU "
        "schedule; paper: method §7 exactly (docs/usage.md)",
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
    add_task_source_options(p, env, hold_out_val=True)


def parser(env: str, default_preset: str = "default") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=f"python -m experiments.{env}",
        description=f"Train and evaluate MPC-PEARL (and its baselines) on the {env} tasks.",
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
    p.add_argument("--out", type=Path, help="run directory (default runs/<env>-<preset>-eps<eps>)")
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


@stoppable
def main(env: str, argv: list[str] | None = None, **extra) -> int:
    """Exit codes: 0 done, 2 a command-line error (config, data, checkpoint, permissions: one
    line on stderr, the traceback with --debug), 1 training diverged, 130 Ctrl-C (128 + the
    signal for SIGTERM, SIGHUP; saved and resumable)."""
    args = parser(env).parse_args(argv)
    from mpcpearl_jax.errors import CheckpointError, RunDirError
    from mpcpearl_jax.training.run import open_session

    def fail(e: BaseException, code: int = 2) -> int:
        if args.debug:
            raise e
        print(f"error: {error_line(e)}", file=sys.stderr, flush=True)
        return code

    if args.tensorboard:
        from mpcpearl_jax.training.livelog import LiveLogError, missing

        if missing():
            return fail(LiveLogError(missing()))
    from mpcpearl_jax.distributed import CoordinatorTimeout, initialize

    try:  # everything up to training: each check names the field, file or folder
        # before any JAX work
        initialize(args.coordinator, args.num_processes, args.process_id, args.coordinator_timeout)
        family = _family(args.env)
        cfg = build_config(args, family, **extra)
        out = args.out or Path("runs") / f"{family}-{args.preset}-{args.algo}-eps{cfg.train.eps:g}"
        print(
            f"[{family}] {run_label(cfg)} preset={args.preset} seeds={cfg.seeds} "
            f"iterations={cfg.train.iterations} out={out}",
            flush=True,
        )
        if args.preset == "default" and args.config is None:
            print(DEFAULT_NOTE, flush=True)
        sess = open_session(
            cfg, out, resume=args.resume, tensorboard=args.tensorboard, overwrite=args.overwrite
        )
    except CoordinatorTimeout as e:  # the runtime's start-up thread would abort the process
        print(f"error: {e}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(2)
    except (ValueError, TypeError, OSError, CheckpointError, RunDirError) as e:
        return fail(e)
    except RuntimeError as e:
        if not out_of_memory(e):
            raise
        return fail(MemoryError(out_of_memory(e)))
    except KeyboardInterrupt:
        print("interrupted before training started", file=sys.stderr, flush=True)
        return stop_exit_code()
    with sess:  # the run folder stays locked until its last file is written
        return _train_and_evaluate(args, sess, fail)


DEFAULT_NOTE = (
    "the default preset: a first look, 75 iterations, about 4-5 minutes of training on a quiet "
    "2-core CPU, longer on a slower or busy one (the README gives the range over ten seeds); the "
    "first iteration compiles, up to a minute of it. Far shorter than the paper's training "
    "(printed under the results table)"
)


def _family(spec: str) -> str:
    """--env's family (`envs.load_family`), its error naming the flag."""
    from mpcpearl_jax.envs import load_family

    try:
        return load_family(spec)
    except ValueError as e:
        raise ValueError(f"--env {e}") from None


def out_of_memory(e: BaseException) -> str:
    """The one line of XLA's out-of-memory error ('' for any other error)."""
    text = str(e)
    if "RESOURCE_EXHAUSTED" not in text or "memory" not in text.lower():
        return ""
    first = text.strip().splitlines()[0]
    return f"out of memory ({first}); lower the config's size fields (--set)"


def _train_and_evaluate(args: argparse.Namespace, sess, fail) -> int:
    from mpcpearl_jax.errors import CheckpointError, RunDirError, TrainingDiverged
    from mpcpearl_jax.evaluation.final import final_evaluation
    from mpcpearl_jax.training.run import RunInterrupted, train_iterations

    cfg, out, trainer = sess.cfg, sess.run_dir, sess.trainer
    start, t0 = sess.done, time.perf_counter()
    try:
        state = train_iterations(sess, progress=not args.no_progress, handle_sigint=True)
    except RunInterrupted as e:
        print(str(e), file=sys.stderr, flush=True)
        return stop_exit_code()
    except KeyboardInterrupt:  # a second Ctrl-C: stopped at once, the last checkpoint stands
        print("interrupted; continue with --resume", file=sys.stderr, flush=True)
        return stop_exit_code()
    except (OSError, CheckpointError, RunDirError) as e:
        return fail(e)
    except TrainingDiverged as e:
        return fail(e, 1)
    except RuntimeError as e:
        if not out_of_memory(e):
            raise
        return fail(MemoryError(out_of_memory(e)))
    train_s = time.perf_counter() - t0
    print(f"trained in {train_s:.1f} s; evaluating", flush=True)
    try:
        final_evaluation(trainer, state, out, run_label(cfg))
    except OSError as e:
        return fail(e)
    except KeyboardInterrupt:
        print(
            f"interrupted in the final evaluation; training is saved (iteration "
            f"{cfg.train.iterations}): evaluate it with --resume",
            file=sys.stderr,
            flush=True,
        )
        return stop_exit_code()
    print(trained_line(cfg, train_s, start), flush=True)
    print(LONGER if cfg.env == "restaurant" else LONGER_ANY, flush=True)
    print(f"results, curves and figures in {out}", flush=True)
    return 0


# the recipe of the five-seed comparison (docs/usage.md, "Training longer")
LONGER = (
    "to train longer, the recommended recipe for 24 minutes (docs/usage.md#training-longer): "
    "python -m experiments.learning --preset cpu-explore --set pearl.auto_entropy=true --eps 0.2 "
    "--minutes 24"
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
