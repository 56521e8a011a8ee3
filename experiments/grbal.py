"""GrBAL baseline (Nagabandi et al., ICLR 2019): `python -m experiments.grbal [--env ...]`.

    python -m experiments.grbal --env restaurant --preset cpu --out runs/grbal-cpu
    python -m experiments.grbal --env sidewalk --data path/to/crowds_zara01.txt --preset cpu
    python -m experiments.grbal --out runs/grbal-cpu --preset cpu --resume   # continue
    python -m experiments.grbal --preset cpu --minutes 16   # train for 16 minutes, then evaluate

Meta-trains the learned dynamics model (one inner SGD step on M past transitions, scored on the
K next), collecting with MPPI on the adapted model, then evaluates on the test tasks (after two
adaptation episodes, and online) and the OOD tasks with the method §8 metrics. Writes
metrics.jsonl, checkpoints, learning_curves.png, trajectory figures and results.json into --out
(the files of the other methods: `python -m experiments.compare` reads them).
Any field of `GrbalConfig` can be changed with --set grbal.FIELD=VALUE, a NavConfig field with
--set env.FIELD=VALUE (JSON values).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.grbal.config import PRESETS, GrbalExperimentConfig, preset

ONLINE_HEADLINE = {"sidewalk": True}  # online adaptation is the sidewalk headline (paper)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.grbal",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--env", default="restaurant", choices=("restaurant", "sidewalk"))
    p.add_argument("--preset", default="default", choices=sorted(PRESETS))
    p.add_argument("--iterations", type=int, help="training iterations (fit + collection)")
    p.add_argument(
        "--minutes",
        type=float,
        help="stop training after this many minutes (checkpointed; --resume continues)",
    )
    p.add_argument("--seeds", type=int, help="independent seeds trained in one program")
    p.add_argument("--seed", type=int, help="base seed (seed s uses seed + s)")
    p.add_argument("--data", type=Path, help="sidewalk: an ETH/UCY file (default: synthetic)")
    p.add_argument(
        "--scenarios",
        type=Path,
        metavar="DIR",
        help="restaurant: the paper's own scenarios (a clone of the authors' repository or a "
        "folder with scenarios/X.npy) instead of the generated crowds",
    )
    p.add_argument(
        "--hold-out-val",
        action="store_true",
        help="--scenarios: train on tasks 0-149 only, keeping 150-179 as the val split",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="override a field: grbal.FIELD, env.FIELD or a top-level field (JSON values)",
    )
    p.add_argument("--out", type=Path, help="run directory (default runs/<env>-<preset>-grbal)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true", help="no line per iteration")
    return p


def _value(text: str):
    try:
        v = json.loads(text)
    except json.JSONDecodeError:
        return text
    return tuple(v) if isinstance(v, list) else v


def build_config(args: argparse.Namespace) -> GrbalExperimentConfig:
    g = preset(args.preset)
    top: dict = {"env": args.env, "online_eval": ONLINE_HEADLINE.get(args.env, False)}
    env_over: dict = {}
    grbal: dict = {}
    if args.iterations is not None:
        grbal["iterations"] = args.iterations
    if args.seeds is not None:
        top["seeds"] = args.seeds
    if args.seed is not None:
        top["seed"] = args.seed
    if args.data is not None:
        if args.env != "sidewalk":
            raise ConfigError("--data: only the sidewalk env reads a data file")
        if not args.data.is_file():
            raise ConfigError(f"--data {args.data}: no such file")
        top["data"] = str(args.data)
    if args.hold_out_val and args.scenarios is None:
        raise ConfigError("--hold-out-val applies to --scenarios")
    if args.scenarios is not None:
        if args.env != "restaurant":
            raise ConfigError("--scenarios: the paper's scenarios are restaurant tasks")
        from mpcpearl_jax.envs.restaurant import scenario_options

        try:  # checks the folder and files now; config.json records their sha256
            top["task_options"] = scenario_options(args.scenarios, args.hold_out_val)
        except OSError as e:
            raise ConfigError(str(e)) from e
    for item in args.set:
        key, sep, raw = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item!r}: expected SECTION.FIELD=VALUE")
        section, _, field = key.rpartition(".")
        target = {"grbal": grbal, "env": env_over, "": top}.get(section)
        if target is None:
            raise ConfigError(f"--set {item!r}: unknown section {section!r}; use grbal or env")
        target[field] = _value(raw)
    known = {f.name for f in dataclasses.fields(type(g))}
    if set(grbal) - known:
        raise ConfigError(f"GrbalConfig has no field(s) {sorted(set(grbal) - known)}")
    top_known = {f.name for f in dataclasses.fields(GrbalExperimentConfig)} - {"grbal"}
    if set(top) - top_known:
        raise ConfigError(f"GrbalExperimentConfig has no field(s) {sorted(set(top) - top_known)}")
    return GrbalExperimentConfig(grbal=g.replace(**grbal), env_overrides=env_over, **top)


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        cfg = build_config(args)
    except (ConfigError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from experiments.common import error_line, out_of_memory
    from mpcpearl_jax.errors import CheckpointError, RunDirError
    from mpcpearl_jax.grbal.run import final_evaluation, load_config, train
    from mpcpearl_jax.training.runlock import RunLock

    out = args.out or Path("runs") / f"{args.env}-{args.preset}-grbal"
    g = cfg.grbal
    print(
        f"[{args.env}] GrBAL preset={args.preset} seeds={cfg.seeds} iterations={g.iterations} "
        f"model={'x'.join(map(str, g.hidden))} MPPI {g.num_samples}x{g.mppi_iterations} "
        f"horizon {g.plan_horizon} out={out}",
        flush=True,
    )
    t0 = time.perf_counter()
    progress = None if args.no_progress else (lambda line: print(line, flush=True))
    try:
        if args.resume:
            load_config(out)  # a GrBAL run folder, before the lock creates anything
        with RunLock(out):  # held through the final evaluation (train takes it again)
            budget = None if args.minutes is None else 60.0 * args.minutes
            trainer, state = train(cfg, out, resume=args.resume, progress=progress, budget_s=budget)
            print(f"trained in {time.perf_counter() - t0:.1f} s; evaluating", flush=True)
            final_evaluation(trainer, state, out)
    except (ConfigError, CheckpointError, RunDirError, OSError) as e:
        print(f"error: {error_line(e)}", file=sys.stderr)
        return 2
    except RuntimeError as e:
        if not out_of_memory(e):
            raise
        print(f"error: {out_of_memory(e)}", file=sys.stderr)
        return 2
    print(f"results, curves and figures in {out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
