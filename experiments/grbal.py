"""GrBAL baseline (Nagabandi et al., ICLR 2019): `python -m experiments.grbal [--env ...]`.

    python -m experiments.grbal --env restaurant --preset cpu --out runs/grbal-cpu
    python -m experiments.grbal --env sidewalk --data path/to/crowds_zara01.txt --preset cpu
    python -m experiments.grbal --out runs/grbal-cpu --preset cpu --resume   # continue
    python -m experiments.grbal --preset cpu --minutes 16   # train for 16 minutes, then evaluate

Meta-trains the learned dynamics model (one inner SGD step on M past transitions, scored on the
K next), collecting with MPPI on the adapted model, then evaluates on the test tasks (after two
adaptation episodes, and online) and the OOD tasks with the method §8 metrics. Writes
metrics.jsonl, checkpoints, learning_curves.png, trajectory figures and results.json into --out
(the files of the other methods: `python -m lab.compare` reads them).
Any field of `GrbalConfig` can be changed with --set grbal.FIELD=VALUE, a NavConfig field with
--set env.FIELD=VALUE (JSON values).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from experiments.common import add_run_mode_options, add_task_source_options, exit_interrupted
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.grbal.config import PRESETS, GrbalExperimentConfig, resolve
from mpcpearl_jax.cli.stopping import stoppable


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
    add_task_source_options(p, hold_out_val=True)
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="override a field: grbal.FIELD, env.FIELD or a top-level field (JSON values)",
    )
    p.add_argument("--out", type=Path, help="run directory (default runs/<env>-<preset>-grbal)")
    add_run_mode_options(p)
    p.add_argument("--no-progress", action="store_true", help="no line per iteration")
    return p


def build_config(args: argparse.Namespace) -> GrbalExperimentConfig:
    if args.data is not None and args.env != "sidewalk":
        raise ConfigError("--data: only the sidewalk env reads a data file")
    changes = {
        key: value
        for key, value in (
            ("grbal.iterations", args.iterations),
            ("seeds", args.seeds),
            ("seed", args.seed),
        )
        if value is not None
    }
    return resolve(
        args.preset,
        args.env,
        changes=changes,
        overrides=args.set,
        scenarios=args.scenarios,
        hold_out_val=args.hold_out_val,
        data=args.data,
    )


@stoppable
def main(argv: list[str] | None = None) -> int:
    """The command; a stop signal (Ctrl-C, SIGTERM, SIGHUP) ends it with one line and exit code
    128 + the signal, the run folder closed (`Session.__exit__`). During training the first
    signal finishes the iteration under way and saves it ("interrupted at iteration N; continue
    with --resume"); a second one, or one during start-up or the final evaluation, stops at once
    with the last checkpoint kept."""
    run: dict[str, Path] = {}  # the run folder, once known
    try:
        return _main(argv, run)
    except KeyboardInterrupt:
        if "out" in run and (run["out"] / "config.json").is_file():
            line = (
                "interrupted: the same command with --resume continues from the run's last "
                "checkpoint (written every checkpoint_interval iterations; from the start if none)"
            )
        else:
            line = "interrupted before the run started; the same command starts it again"
        exit_interrupted(line)


def _main(argv: list[str] | None, run: dict[str, Path]) -> int:
    args = parser().parse_args(argv)
    try:
        cfg = build_config(args)
    except (ConfigError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from experiments.common import one_line_errors
    from mpcpearl_jax.grbal.run import GRBAL, final_evaluation, train_iterations
    from mpcpearl_jax.training.run import open_session

    out = args.out or Path("runs") / f"{args.env}-{args.preset}-grbal"
    run["out"] = Path(out)
    g = cfg.grbal
    print(
        f"[{args.env}] GrBAL preset={args.preset} seeds={cfg.seeds} iterations={g.iterations} "
        f"model={'x'.join(map(str, g.hidden))} MPPI {g.num_samples}x{g.mppi_iterations} "
        f"horizon {g.plan_horizon} out={out}",
        flush=True,
    )
    t0 = time.perf_counter()
    progress = None if args.no_progress else (lambda line: print(line, flush=True))
    # errors as one line; a stop signal: the iteration under way finished and saved
    with one_line_errors(interrupted=None) as outcome:
        # the run folder stays locked through the final evaluation
        with open_session(cfg, out, args.resume, kind=GRBAL, overwrite=args.overwrite) as sess:
            budget = None if args.minutes is None else 60.0 * args.minutes
            state = train_iterations(sess, progress, budget, handle_sigint=True)
            print(f"trained in {time.perf_counter() - t0:.1f} s; evaluating", flush=True)
            final_evaluation(sess.trainer, state, out)
    if outcome.code is not None:
        return outcome.code
    print(f"results, curves and figures in {out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
