"""The training commands (`python -m experiments.restaurant`, `.sidewalk`, `.learning`, and an
algorithm's own, `.grbal`): one `main` for every registered algorithm (`mpcpearl_jax.algorithms`)
parses its command line (`cli.args`), calls the one entry `mpcpearl_jax.train` with its options
and callbacks (`TrainOptions`), prints what they report and chooses the exit code: 0 done, 2 a
command-line error (config, data, checkpoint, permissions: one line on stderr, the traceback with
--debug), 1 training diverged, 128 + the signal for a stop (130: Ctrl-C; resumable)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from mpcpearl_jax import cli
from mpcpearl_jax.api.train import TrainOptions, train
from mpcpearl_jax.cli.args import algorithm_of, budget_error, build_config, env_family, parse_args
from mpcpearl_jax.cli.errors import fail_line, one_line_errors
from mpcpearl_jax.cli.platform import check_platform
from mpcpearl_jax.cli.progress import progress_bar
from mpcpearl_jax.cli.stopping import exit_interrupted, stop_exit_code, stoppable
from mpcpearl_jax.cli.tables import curve_summary, print_point
from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.errors import RunDirError, TrainingDiverged
from mpcpearl_jax.evaluation.report import run_label
from mpcpearl_jax.runfolder import CONFIG_FILE
from mpcpearl_jax.training.budget import default_label
from mpcpearl_jax.training.run import RunInterrupted


@stoppable
def main(
    env: str,
    argv: list[str] | None = None,
    *,
    algorithm: Any = None,
    command: str | None = None,
    from_config: bool = False,
    description: str | None = None,
    clock=time.perf_counter,
    **extra,
) -> int:
    """The training command of `algorithm` (a registered name or object; default MPC-PEARL) for
    family `env` (an algorithm's own command: the default of its --env; exit codes: the module
    doc). `description`: the help's text; `clock` times a --minutes budget (tests give a fake
    one); `extra`: config fields (`build_config`)."""
    cli.setup()
    algorithm = algorithm_of(algorithm)
    args = parse_args(
        env,
        argv,
        command=command,
        from_config=from_config,
        algorithm=algorithm,
        description=description,
    )

    def fail(e: BaseException, code: int = 2) -> int:
        return fail_line(e, code, args.debug)

    if budget_error(args, algorithm.learning_curve):
        return fail(ValueError(budget_error(args, algorithm.learning_curve)))
    if args.tensorboard:
        from mpcpearl_jax.training.livelog import LiveLogError, missing

        if missing():
            return fail(LiveLogError(missing()))
    if args.print_config:
        try:
            cfg = build_config(args, env_family(args.env), algorithm=algorithm, **extra)
        except (ValueError, TypeError, OSError) as e:
            return fail(e)
        print(cfg.to_json(), flush=True)
        return 0
    run = _Run(args, clock, algorithm)
    try:  # each check names the field, file or folder; errors and stops as one line
        with one_line_errors(args.debug, interrupted=None) as outcome:
            _initialize(args)  # before any JAX work
            check_platform()  # JAX_PLATFORMS naming a platform this machine lacks: one line
            cfg = build_config(args, env_family(args.env), algorithm=algorithm, **extra)
            family = cfg.env  # the run's, where a resume continues on it
            if algorithm.run_folder is None:  # the run's label names its folder
                label = args.label or default_label(family, args.preset, args.algo, cfg.train.eps)
                folder: str = label
            else:  # the algorithm's label names the run
                label, folder = (
                    args.label,
                    algorithm.run_folder.format(env=family, preset=args.preset),
                )
            out = run.out = args.out or Path("runs") / folder
            finished = finished_line(out, cfg, args.minutes) if args.resume else None
            if finished is not None:  # nothing to train or evaluate: no file is touched
                print(finished, flush=True)
                return 0
            try:
                _print_start(args, algorithm, family, cfg, label or folder, out)
            except BrokenPipeError:
                return run.output_closed(out, finished=False)
            try:
                _, results = train(cfg, out, args.minutes, label=label, options=run.options())
            except (RunInterrupted, TrainingDiverged, KeyboardInterrupt) as e:
                return run.stopped(e, cfg, label, out)
            except (BrokenPipeError, RunDirError) as e:
                if not output_closed(e):
                    raise
                return run.output_closed(out, finished=False)
            try:
                return run.report(cfg, results, label, out)
            except BrokenPipeError:
                return run.output_closed(out, finished=True)
    except KeyboardInterrupt:  # a stop before training, or a second one during it
        return run.interrupted()
    finally:
        run.close_bar()
    return outcome.code  # type: ignore[return-value]


class _Run:
    """One training of the command: `mpcpearl_jax.train` with the command's callbacks (the
    progress bar or the algorithm's line per iteration, the eval points' lines), then its lines
    and exit code."""

    def __init__(self, args: argparse.Namespace, clock, algorithm: Any) -> None:
        self.args, self.clock, self.algorithm = args, clock, algorithm
        # a time budget with its learning curve (otherwise --minutes stops the iterations early)
        self.curve = args.minutes is not None and algorithm.learning_curve
        self.line = None if args.no_progress else algorithm.progress_line
        self.start: int | None = None  # iterations finished when the session opened
        self.cfg: Any = None
        self.out: Path | None = None  # the run folder, once known
        self.info: dict[str, Any] = {}
        self.bar: Any = None
        self.t0 = self.train_s = 0.0

    def close_bar(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def on_start(self, sess) -> None:
        self.start, self.t0, self.cfg = sess.done, time.perf_counter(), sess.cfg
        if not self.curve and not self.args.no_progress and self.line is None:
            self.bar = progress_bar(sess.cfg, sess.done)

    def on_row(self, row: dict[str, Any]) -> None:
        if self.bar is not None:
            self.bar.row(row)
        elif self.line is not None:
            print(self.line(row, self.cfg), flush=True)

    def on_trained(self, info: dict[str, Any]) -> None:
        self.close_bar()
        self.info, self.train_s = info, time.perf_counter() - self.t0
        if not self.curve and info["stopped"] == "budget" and self.line is not None:
            print(
                f"time budget of {60.0 * self.args.minutes:.0f} s reached after iteration "
                f"{info['iterations']}",
                flush=True,
            )
        if not self.curve and info["stopped"] in ("done", "budget"):
            if info["iterations"] == self.start:  # a resume of a run stopped in its evaluation
                print(f"all {self.start} iteration(s) trained before; evaluating", flush=True)
            else:
                print(f"trained in {self.train_s:.1f} s; evaluating", flush=True)
        if info["stopped"].startswith("diverged") and self.curve:
            print(f"error: {info['error']}", file=sys.stderr, flush=True)  # the curve follows

    def options(self):
        """`mpcpearl_jax.train`'s options: the command line's, and the callbacks above."""
        args = self.args
        return TrainOptions(
            resume=args.resume,
            overwrite=args.overwrite,
            eval_minutes=args.eval_minutes,
            policy_only=args.policy_only,
            tensorboard=args.tensorboard,
            record={"preset": args.preset, "argv": args.argv} if self.curve else {},
            clock=self.clock,
            on_start=self.on_start,
            on_row=self.on_row,
            on_point=print_point,
            on_trained=self.on_trained,
        )

    def interrupted(self) -> int:
        """A stop outside the saved stop of training (during start-up, a second signal, during
        the final evaluation): its one line and exit code. An algorithm's own command names the
        command that goes on, by whether the run's config.json is written; the task families'
        commands say where the run stopped."""
        self.close_bar()
        if self.algorithm.command is not None:
            if self.out is not None and (self.out / CONFIG_FILE).is_file():
                exit_interrupted(
                    "interrupted: the same command with --resume continues from the run's last "
                    "checkpoint (written every checkpoint_interval iterations; from the start if "
                    "none)"
                )
            exit_interrupted("interrupted before the run started; the same command starts it again")
        if self.start is None:  # the session closed what it had opened
            exit_interrupted("interrupted before training started")
        print("interrupted; continue with --resume", file=sys.stderr, flush=True)
        return stop_exit_code()

    def output_closed(self, out: Path, finished: bool) -> int:
        """stdout closed under the command (a pipe's reader gone: `| head`): one line on stderr
        saying what is saved and how --resume finishes it, exit code 2."""
        if finished:
            line = f"the run is finished: results, curves and figures in {out}"
        elif self.info.get("stopped") in ("done", "budget"):
            line = (
                f"training is saved ({self.info['iterations']} iterations) but not evaluated: "
                "the same command with --resume runs the final evaluation"
            )
        elif self.start is not None:
            line = "the same command with --resume continues from the run's last checkpoint"
        else:
            line = "nothing was trained; the same command starts again"
        _quiet_stdout()
        with contextlib.suppress(OSError):
            print(f"error: the output closed (broken pipe); {line}", file=sys.stderr, flush=True)
        return 2

    def stopped(self, e: BaseException, cfg: Any, label: str | None, out: Path) -> int:
        """A stop signal or a divergence: its line and exit code (or `e` raised again for the
        error ladder: a divergence on iterations, a second stop during training)."""
        args, info = self.args, self.info
        if isinstance(e, RunInterrupted):
            line = str(RunInterrupted(info["iterations"], info.get("lost", 0)))
            if args.policy_only:
                line = (
                    f"interrupted at iteration {info['iterations']} (--policy-only: no "
                    "checkpoint to resume from)"
                )
            print(line, file=sys.stderr, flush=True)
            return stop_exit_code()
        if isinstance(e, TrainingDiverged) and self.curve:
            return curve_summary(info, label, out)  # its error line printed above
        own = self.algorithm.command is not None  # its stop lines: `interrupted`
        if isinstance(e, KeyboardInterrupt) and not self.curve and info and not own:
            print(
                f"interrupted in the final evaluation; training is saved (iteration "
                f"{self.algorithm.iterations(cfg)}), not yet evaluated: the same command with "
                "--resume runs the final evaluation",
                file=sys.stderr,
                flush=True,
            )
            return stop_exit_code()
        raise e

    def report(self, cfg: Any, results: dict, label: str | None, out: Path) -> int:
        """The results table (and the paper's note that results.json carries), then the curve's
        summary, or what was trained and how to train longer (the task families' commands), and
        where the run is."""
        from mpcpearl_jax.distributed import is_primary
        from mpcpearl_jax.evaluation.report import results_table

        if results and is_primary():
            print(results_table(results))
        if results.get("paper_note"):
            print(results["paper_note"])
        if self.curve:
            return curve_summary(self.info, label, out)
        if self.algorithm.command is None:
            print(trained_line(cfg, self.train_s, self.start or 0, self.info), flush=True)
            print(LONGER if cfg.env == "restaurant" else LONGER_ANY, flush=True)
        print(f"results, curves and figures in {out}", flush=True)
        return 0


def output_closed(e: BaseException) -> bool:
    """Whether `e` is the command's stdout closed under it (BrokenPipeError, also as the cause
    of the run's write error it became inside the training loop)."""
    return isinstance(e, BrokenPipeError) or isinstance(e.__cause__, BrokenPipeError)


def _quiet_stdout() -> None:
    """stdout to /dev/null, so the interpreter's exit does not flush into the closed pipe."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())


def finished_line(out: Path, cfg: ExperimentConfig, minutes: float | None = None) -> str | None:
    """For --resume: the one line that says the run in `out` is finished, or None where there
    is something to train or evaluate. On iterations: results.json written for the config's
    iterations, every one of them logged; on a time budget (`minutes`): results.json written
    and curve.json's budget spent, and `minutes` no larger than it."""
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


def _print_start(
    args: argparse.Namespace, algorithm: Any, family: str, cfg, label: str, out: Path
) -> None:
    """The command's first line: what it trains, how long, into which folder (and the preset's
    note, `Algorithm.notes`, where it trains as it is)."""
    if args.minutes is not None and algorithm.learning_curve:
        from mpcpearl_jax.training.budget import eval_every_minutes

        every = eval_every_minutes(args.minutes, args.eval_minutes)
        print(
            f"[{family}] {algorithm.label(cfg)} {label}: preset={args.preset} seeds={cfg.seeds} "
            f"budget={args.minutes:g} min, eval every {every:.3g} min "
            f"({'online' if cfg.online_eval else 'adaptation'} protocol), out={out}"
            + (" (resumed)" if args.resume else ""),
            flush=True,
        )
        return
    summary = f"{algorithm.summary(cfg)} " if algorithm.summary is not None else ""
    print(
        f"[{family}] {algorithm.label(cfg)} preset={args.preset} seeds={cfg.seeds} "
        f"iterations={algorithm.iterations(cfg)} {summary}out={out}",
        flush=True,
    )
    note = algorithm.notes.get(args.preset)
    if note and args.config is None and args.iterations is None:
        print(note, flush=True)  # its figures are for the preset's own iterations


# the recipe of the five-seed comparison (docs/usage.md, "Training longer")
LONGER = (
    "to train longer (docs/usage.md, 'Training longer'): python -m experiments.restaurant "
    "--preset recipe --eps 0.2 --minutes 24"
)
LONGER_ANY = "to train longer: --iterations N, or another preset (docs/usage.md#training-longer)"


def trained_line(
    cfg: ExperimentConfig, seconds: float, start: int = 0, info: dict | None = None
) -> str:
    """What this process trained, for how long and on what (printed under the results table,
    whose paper columns say how long the paper trained). A resumed run whose iterations were
    all trained before (stopped during its final evaluation) says so: its iterations and the
    training time of its earlier processes (`info["train_s"]`, the run's lifetime)."""
    import jax

    iters = cfg.train.iterations - start
    dev = jax.devices()[0]
    where = (
        f"a {os.cpu_count()}-core CPU"
        if dev.platform == "cpu"
        else f"{jax.device_count()} x {dev.device_kind}"
    )
    if iters == 0 and info:  # nothing left to train: evaluated what was trained before
        iters, seconds = cfg.train.iterations, float(info.get("train_s") or 0.0)
        steps = iters * cfg.train.updates_per_iteration
        return (
            f"this run: {run_label(cfg)}, {iters} iteration(s) x "
            f"{cfg.train.updates_per_iteration} gradient steps ({steps:,}), {cfg.seeds} "
            f"seed(s), trained in {seconds / 60:.1f} min before this resume, which evaluated it "
            f"on {where}"
        )
    steps = iters * cfg.train.updates_per_iteration
    return (
        f"this run: {run_label(cfg)}, {iters} iteration(s) x {cfg.train.updates_per_iteration} "
        f"gradient steps ({steps:,}), {cfg.seeds} seed(s), trained in {seconds / 60:.1f} min on "
        f"{where}"
    )
