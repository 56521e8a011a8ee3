"""Command-line interface shared by the experiment entry points."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
import typing
from pathlib import Path

from mpcpearl_jax.config import PRESETS, ExperimentConfig, TrainConfig, preset, validate
from mpcpearl_jax.envs import can_redraw, mpc_defaults
from mpcpearl_jax.envs.types import NavConfig
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.evaluation.report import run_label
from mpcpearl_jax.mpc.config import MPCConfig
from mpcpearl_jax.pearl.config import PearlConfig

# Config extras each environment's entry point passes to `build_config` (and `main`).
ENV_EXTRAS: dict[str, dict] = {
    "restaurant": {},
    # online adaptation is the sidewalk headline (as in the paper); the family's MPC defaults
    # (`envs.mpc_defaults`) come with its registration
    "sidewalk": {"online_eval": True},
}


def add_config_options(
    p: argparse.ArgumentParser, env: str, default_preset: str = "default"
) -> None:
    """The options `build_config` reads: --preset, --eps, --seeds, --seed, --algo, --set
    (and --data for the sidewalk). Shared with `experiments.learning`."""
    p.add_argument(
        "--preset",
        default=default_preset,
        choices=sorted(PRESETS),
        help="smoke: ~2 min pipeline check; default: a few minutes on a laptop CPU; "
        "cpu: an hours-long CPU schedule; paper: method §7 exactly",
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
    if env == "restaurant":
        p.add_argument(
            "--scenarios",
            type=Path,
            metavar="DIR",
            help="train and evaluate on the paper's own scenarios: a clone of the authors' "
            "repository or a folder with scenarios/X.npy (and optionally "
            "scenarios_out_of_distribution/X.npy); default: the project's crowd generator",
        )
        p.add_argument(
            "--hold-out-val",
            action="store_true",
            help="--scenarios: train on tasks 0-149 only, keeping 150-179 as the val split",
        )
    if env == "sidewalk":
        p.add_argument(
            "--data",
            type=Path,
            help="an ETH/UCY trajectory file (e.g. UCY "
            "crowds_zara01.txt); default: the built-in synthetic crowd",
        )


def parser(env: str, default_preset: str = "default") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=f"python -m experiments.{env}",
        description=f"Train and evaluate MPC-PEARL (and its baselines) on the {env} tasks.",
    )
    add_config_options(p, env, default_preset)
    p.add_argument("--iterations", type=int, help="meta-training iterations")
    p.add_argument("--out", type=Path, help="run directory (default runs/<env>-<preset>-eps<eps>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
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


def _parse_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


_SECTION_CLASSES = {
    "pearl": PearlConfig,
    "train": TrainConfig,
    "mpc": MPCConfig,
    "env_overrides": NavConfig,
    "": ExperimentConfig,
}
_TRUE, _FALSE = ("true", "True", "1"), ("false", "False", "0")


def _field_value(item: str, section: str, field: str, text: str):
    """The value of `--set item` for a field, read by the field's type: booleans (true/false,
    True/False, 1/0) only for bool fields, never for numbers; None/null for optional fields."""
    cls = _SECTION_CLASSES[section]
    hints = typing.get_type_hints(cls)
    if field not in hints or field not in {f.name for f in dataclasses.fields(cls)}:
        raise ConfigError(f"--set {item}: {cls.__name__} has no field(s) {[field]}")
    hint = hints[field]
    name = f"{cls.__name__}.{field}"
    args = typing.get_args(hint)
    if hint is bool:
        if text in _TRUE:
            return True
        if text in _FALSE:
            return False
        raise ConfigError(f"--set {item}: {name} must be true or false, got {text!r}")
    if type(None) in args and text in ("None", "null"):
        return None
    v = _parse_value(text)
    numeric = {int, float} & ({hint} | set(args))
    if numeric and (isinstance(v, bool) or text in ("True", "False")):
        kind = "an int" if numeric == {int} else "a number"
        raise ConfigError(f"--set {item}: {name} must be {kind}, not a boolean")
    return tuple(v) if isinstance(v, list) else v


def build_config(args: argparse.Namespace, env: str, **extra) -> ExperimentConfig:
    base = preset(args.preset)
    scenarios = getattr(args, "scenarios", None)
    if getattr(args, "hold_out_val", False) and scenarios is None:
        raise ConfigError("--hold-out-val applies to --scenarios")
    if args.preset == "default" and (scenarios is not None or not can_redraw(env)):
        # the main command runs on every family: the default re-draws crowds where the family
        # can (the restaurant); a recorded crowd (the sidewalk, the paper's scenarios) is kept
        base = base.replace(train=dataclasses.replace(base.train, redraw_behaviours=False))
    if scenarios is not None:
        from mpcpearl_jax.envs.restaurant import scenario_options

        # checks the folder and its files now, and records their sha256 in config.json
        extra = {**extra, "task_options": scenario_options(scenarios, args.hold_out_val)}
    # the family's MPC defaults (its registration), then the caller's, on top of the preset's
    extra = {**extra, "mpc": base.mpc.replace(**{**mpc_defaults(env), **extra.get("mpc", {})})}
    cfg = base.replace(env=env, **extra)
    sections: dict[str, dict] = {
        "pearl": {},
        "train": {},
        "mpc": {},
        "env_overrides": dict(cfg.env_overrides),
        "": {},
    }
    if args.eps is not None:
        sections["train"]["eps"] = args.eps
    if getattr(args, "iterations", None) is not None:
        sections["train"]["iterations"] = args.iterations
    if args.seeds is not None:
        sections[""]["seeds"] = args.seeds
    if args.seed is not None:
        sections[""]["seed"] = args.seed
    if getattr(args, "devices", None) is not None:
        sections[""]["devices"] = args.devices
    if getattr(args, "data", None) is not None:
        if not Path(args.data).is_file():
            raise ConfigError(f"--data {args.data}: no such file")
        sections[""]["data"] = str(args.data)
    if args.algo == "sac":
        sections["pearl"]["use_context"] = False
    for item in args.set:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected SECTION.FIELD=VALUE")
        key, value = item.split("=", 1)
        section, _, field = key.rpartition(".")
        if section == "env":
            section = "env_overrides"
        if section not in sections:
            raise ConfigError(
                f"--set {item!r}: unknown section {section!r}; use pearl, train, "
                "mpc, env or a top-level field"
            )
        sections[section][field] = _field_value(item, section, field, value)
    for name, cls in (("pearl", type(cfg.pearl)), ("train", type(cfg.train))):
        unknown = set(sections[name]) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ConfigError(f"{cls.__name__} has no field(s) {sorted(unknown)}")
    top_unknown = set(sections[""]) - {f.name for f in dataclasses.fields(ExperimentConfig)}
    if top_unknown:
        raise ConfigError(f"ExperimentConfig has no field(s) {sorted(top_unknown)}")
    return cfg.replace(
        pearl=cfg.pearl.replace(**sections["pearl"]),
        train=dataclasses.replace(cfg.train, **sections["train"]),
        mpc=cfg.mpc.replace(**sections["mpc"]),
        env_overrides=sections["env_overrides"],
        **sections[""],
    )


def error_line(e: BaseException) -> str:
    """One line for a command-line error: OSErrors name their file, others carry their own."""
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or type(e).__name__}"
    if isinstance(e, UnicodeDecodeError):
        return f"not a text file ({e.reason} at byte {e.start})"
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


def main(env: str, argv: list[str] | None = None, **extra) -> int:
    """Exit codes: 0 done, 2 a command-line error (config, data, checkpoint, permissions: one
    line on stderr, the traceback with --debug), 1 training diverged, 130 Ctrl-C (resumable)."""
    args = parser(env).parse_args(argv)
    from mpcpearl_jax.errors import CheckpointError, RunDirError
    from mpcpearl_jax.training.run import prepare

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
        cfg = validate(build_config(args, env, **extra))
        out = args.out or Path("runs") / f"{env}-{args.preset}-{args.algo}-eps{cfg.train.eps:g}"
        print(
            f"[{env}] {run_label(cfg)} preset={args.preset} seeds={cfg.seeds} "
            f"iterations={cfg.train.iterations} out={out}",
            flush=True,
        )
        sess = prepare(cfg, out, resume=args.resume)
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
        return 130
    try:  # the run folder stays locked until its last file is written
        return _train_and_evaluate(args, sess, fail)
    finally:
        sess.lock.release()


def out_of_memory(e: BaseException) -> str:
    """The one line of XLA's out-of-memory error ('' for any other error)."""
    text = str(e)
    if "RESOURCE_EXHAUSTED" not in text or "memory" not in text.lower():
        return ""
    first = text.strip().splitlines()[0]
    return f"out of memory ({first}); lower the config's size fields (--set)"


def _train_and_evaluate(args: argparse.Namespace, sess, fail) -> int:
    from mpcpearl_jax.errors import CheckpointError, RunDirError, TrainingDiverged
    from mpcpearl_jax.training.run import RunInterrupted, final_evaluation, train_session

    cfg, out = sess.cfg, sess.run_dir
    t0 = time.perf_counter()
    try:
        trainer, state = train_session(
            sess, progress=not args.no_progress, handle_sigint=True, tensorboard=args.tensorboard
        )
    except RunInterrupted as e:
        print(str(e), file=sys.stderr, flush=True)
        return 130
    except KeyboardInterrupt:  # a second Ctrl-C: stopped at once, the last checkpoint stands
        print("interrupted; continue with --resume", file=sys.stderr, flush=True)
        return 130
    except (OSError, CheckpointError, RunDirError) as e:
        return fail(e)
    except TrainingDiverged as e:
        return fail(e, 1)
    except RuntimeError as e:
        if not out_of_memory(e):
            raise
        return fail(MemoryError(out_of_memory(e)))
    print(f"trained in {time.perf_counter() - t0:.1f} s; evaluating", flush=True)
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
        return 130
    print(f"results, curves and figures in {out}", flush=True)
    return 0
