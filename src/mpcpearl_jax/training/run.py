"""The run session, the one run driver: `open_session` opens a run folder (every check, the
lock, the restored state, the log cut back to it, progress rebuilt from it, TensorBoard),
`Session.train` trains under a caller's rules and its one callback per row (the one training
loop, `loop.train_loop`, with logging, Ctrl-C and write errors handled), `Session.close` closes
it (checkpointer, the MPC bridge's worker pool, TensorBoard, lock). Its users keep only their
rules: the iterations mode (`train_iterations`), training on a time budget (`training.budget`,
`--minutes`) and GrBAL (`grbal.run`, with its own `RunKind`), all three run by the one entry
`mpcpearl_jax.train` (`training.final`), which then writes results.json and the figures.

Resume is exact: everything that shapes the rest of a run is in the checkpointed TrainState or
rebuilt deterministically from the config, so a run stopped at any moment (kill -9, Ctrl-C, power
loss) and resumed ends bit-identical to one never stopped. metrics.jsonl is appended one whole line
at a time; rows beyond the restored checkpoint are recomputed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import jax

from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.distributed import first_local, is_primary, to_host
from mpcpearl_jax.errors import CheckpointError, RunDirError
from mpcpearl_jax.pearl.learner import acting_params
from mpcpearl_jax.runfolder import (
    LOG_FILE,
    RUN_RECORDS,
    append_log,
    load_config,
    read_log,
    save_config,
    save_network,
    warn,
    write_log,
)
from mpcpearl_jax.training.checkpoint import (
    Checkpointer,
    check_resumable,
    committed_steps,
    remove_partial,
    resume_hint,
)
from mpcpearl_jax.training.loop import Progress, train_loop
from mpcpearl_jax.training.protocol import TrainerProtocol
from mpcpearl_jax.training.resources import _size, check_state_fits, tree_bytes
from mpcpearl_jax.training.runlock import LOCK_FILE, RunLock
from mpcpearl_jax.training.stopping import StopNow, stop_flag
from mpcpearl_jax.training.trainer import IterationAbandoned, Trainer, TrainState
from mpcpearl_jax.validate import not_writable


class RunInterrupted(Exception):
    """Training stopped by a stop signal (Ctrl-C, SIGTERM, SIGHUP); `iteration` iterations are
    saved and resumable."""

    def __init__(self, iteration: int, lost: int = 0):
        self.iteration, self.lost = iteration, lost
        span = f"{iteration + 1}-{iteration + lost}" if lost > 1 else f"{iteration + 1}"
        extra = f" (iteration(s) {span}, finished after the last checkpoint, are redone)"
        extra = extra if lost else ""
        super().__init__(f"interrupted at iteration {iteration}; continue with --resume{extra}")


def write_error(e: OSError, saved: int) -> RunDirError:
    """A failed write during training (a full disk, an I/O error) as one line: the file, the
    cause, and the iteration a resume starts from (saved: the newest checkpoint, -1: none)."""
    where = e.filename or "the run folder"
    return RunDirError(f"{where}: cannot write ({e.strerror or e}); {resume_hint(saved)}")


def check_writable(run_dir: Path) -> None:
    """Create run_dir and run_dir/checkpoints if needed and prove both writable (a probe file is
    written and removed); RunDirError naming the folder otherwise."""
    for d in (run_dir, run_dir / "checkpoints"):
        try:
            d.mkdir(parents=True, exist_ok=True)
            probe = d / f".write-probe-{os.getpid()}"
            with open(probe, "wb") as f:
                f.write(b"probe")
            probe.unlink()
        except OSError as e:
            raise RunDirError(not_writable(d, e)) from e


class RunKind(Protocol):
    """What differs between the kinds of run a session trains (`PEARL` here, `grbal.run.GRBAL`):
    the config section that holds `iterations` and `keep_checkpoints` ('train'), how a run
    folder's config is read, how the trainer is built and checked against the free memory, what
    policy.msgpack holds, and whether network.json (what `load_policy` needs) is written."""

    section: str
    network_file: bool

    def load_config(self, run_dir: Path, resume: bool) -> Any: ...

    def make_trainer(self, cfg: Any) -> Any: ...

    def check_fits(self, trainer: Any) -> None: ...  # ConfigError when its state won't fit

    def saved_params(self, trainer: Any, state: Any) -> Any: ...


def _section(kind: RunKind, cfg: Any) -> Any:
    return getattr(cfg, kind.section)


class PearlRun:
    """MPC-PEARL's `RunKind`: `Trainer`, its {policy, encoder} in policy.msgpack, network.json."""

    section = "train"
    network_file = True

    def load_config(self, run_dir: Path, resume: bool) -> ExperimentConfig:
        return load_config(run_dir, resume=resume)

    def make_trainer(self, cfg: ExperimentConfig) -> Trainer:
        return Trainer(cfg)

    def check_fits(self, trainer: Trainer) -> None:
        check_state_fits(  # before anything is allocated
            trainer.init_state,
            "the training state (replay buffers, networks)",
            lambda shapes: state_blame(trainer, shapes),
        )

    def saved_params(self, trainer: Trainer, state: TrainState) -> dict:
        return policy_params(state)


PEARL = PearlRun()


def state_blame(trainer: Trainer, shapes: Any) -> tuple[str, str]:
    """What makes MPC-PEARL's training state (`shapes`: its `jax.eval_shape`) large, for the
    memory check's line: -> (the fields to lower, what needs the memory). The replay buffers
    grow with train.rl_capacity, the training tasks, the seeds and the observation's size
    (env fields above their defaults, e.g. env.observe_forecast); the networks with the pearl
    size fields above their defaults (e.g. pearl.crowd_dim). The larger part's fields first."""
    from mpcpearl_jax.envs.types import NavConfig
    from mpcpearl_jax.pearl.config import PearlConfig
    from mpcpearl_jax.training.resources import dataclass_defaults, grown_fields

    cfg = trainer.cfg
    buffers = tree_bytes(shapes.rl) + tree_bytes(shapes.enc)
    nets = tree_bytes(shapes) - buffers
    env = (
        dataclasses.asdict(trainer.env.config)
        if dataclasses.is_dataclass(trainer.env.config)
        else {}
    )
    observation = grown_fields(
        {k: env.get(k, v) for k, v in cfg.env_overrides.items()},
        dataclass_defaults(NavConfig),
        "env",
    )
    network = grown_fields(dataclasses.asdict(cfg.pearl), dataclass_defaults(PearlConfig), "pearl")
    data = [*observation, "train.rl_capacity, the training tasks or the seeds"]
    leaves = jax.tree_util.tree_leaves(shapes.learner.params)
    params = sum(math.prod(x.shape) for x in leaves) // max(cfg.seeds, 1)
    what = (
        f"the training state (replay buffers {_size(buffers)}: observations of "
        f"{trainer.obs_dim:,} numbers; networks {_size(nets)}: {params:,} parameters per seed)"
    )
    parts = [data, network] if buffers >= nets or not network else [network, data]
    return ", or ".join(", ".join(p) for p in parts if p), what


def _never(*_: Any) -> bool:
    return False


def _nothing(*_: Any) -> None:
    return None


@dataclasses.dataclass
class Session:
    """One run folder, open for training: every check passed, the folder locked (one writer),
    the state restored, config.json written, metrics.jsonl cut back to the restored iteration
    and `progress` rebuilt from it. `train(...)` runs the one training loop under a caller's
    rules; `close()` (or leaving a `with` block) closes the checkpointer, the trainer (the MPC
    bridge's worker pool), TensorBoard and the lock.

    `open_session` builds one for a run folder. Built directly (no `ckpt`, no `lock`), a session
    trains a trainer and state into `run_dir`'s metrics.jsonl without checkpoints."""

    cfg: Any
    run_dir: Path
    trainer: TrainerProtocol
    state: Any
    rows: list[dict] = dataclasses.field(default_factory=list)
    ckpt: Checkpointer | None = None
    lock: RunLock | None = None
    kind: RunKind = PEARL
    tb: Any = None  # a livelog.TensorBoardLog, every row mirrored into it
    progress: Progress = dataclasses.field(init=False)

    def __post_init__(self) -> None:
        # finished iterations, and the newest checkpoint's iteration (-1: none restored)
        self.done = (
            int(first_local(self.state.iteration)) if hasattr(self.state, "iteration") else 0
        )
        self.saved = getattr(self.ckpt, "restored_step", -1)
        # a resumed run's clocks go on from its last kept iteration row: train_s and wall_s are
        # over the run's lifetime (metrics.jsonl), not over this process
        kept = [r for r in self.rows if "train_s" in r]
        self.progress = Progress(
            iterations=self.done,
            saved=self.saved,
            train_s=float(kept[-1]["train_s"]) if kept else 0.0,
            wall_s0=float(kept[-1].get("wall_s", 0.0)) if kept else 0.0,
            first_iteration_s=float(kept[0]["train_s"]) if kept else None,
        )

    @property
    def log_path(self) -> Path:
        return self.run_dir / LOG_FILE

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Close what the session holds; safe to call more than once (the trainer stays usable:
        a later MPC call starts its worker pool again)."""
        if self.ckpt is not None:
            self.ckpt.close()
            self.ckpt = None
        if hasattr(self.trainer, "close"):
            self.trainer.close()
        if self.tb is not None:
            self.tb.close()
            self.tb = None
        if self.lock is not None:
            self.lock.release()
            self.lock = None

    def save(self, iteration: int, state: Any) -> None:
        """A checkpoint of `state` at `iteration` (orbax TrainState + policy.msgpack)."""
        if self.ckpt is None:
            raise CheckpointError(f"{self.run_dir}: this session keeps no checkpoints")
        self.ckpt.save(iteration, state, self.kind.saved_params(self.trainer, state))

    def log(self, row: dict[str, Any]) -> None:
        """One row of the run: kept in `rows`, appended to metrics.jsonl (process 0) and
        mirrored to TensorBoard."""
        self.rows.append(row)
        if is_primary():
            append_log(self.log_path, row)
        if self.tb is not None:
            self.tb.write(row)

    def train(
        self,
        *,
        until: Callable[[Progress], bool],
        on_row: Callable[[dict[str, Any], Any, Progress], dict[str, Any] | None] = _nothing,
        checkpoint_after: Callable[[Progress, bool], bool] = _never,
        save: Callable[[int, Any], None] | None | str = "checkpoint",
        handle_sigint: bool = False,
        clock: Callable[[], float] = time.perf_counter,
    ) -> Any:
        """Train under the caller's rules (`loop.train_loop`: until and the checkpoint schedule)
        and return the state. After every iteration the caller's one callback, `on_row(row,
        state, progress)`, evaluates when its rule says so (always when `progress.last`),
        returning the evaluation's fields (None: not evaluated), and reports; the session then
        logs the row (`log`). save: "checkpoint" (the session's checkpointer), a function
        (iteration, state), or None (no saves).

        With handle_sigint, Ctrl-C stops at the next phase boundary, saves the last finished
        iteration if it is still in memory, and raises RunInterrupted, also when it came during
        the iteration that ends the training (a second Ctrl-C: KeyboardInterrupt at once). A
        failed write (a full disk) raises RunDirError naming the file and the iteration a
        resume starts from; TrainingDiverged propagates."""
        saver = self.save if save == "checkpoint" else save
        where = self.progress
        with stop_flag(handle_sigint, where) as stop:
            try:
                self.state = train_loop(
                    self.trainer,
                    self.state,
                    where,
                    until=until,
                    on_row=on_row,
                    log=self.log,
                    save=saver,  # type: ignore[arg-type]
                    checkpoint_after=checkpoint_after,
                    stop=stop,
                    clock=clock,
                )
            except (IterationAbandoned, StopNow):  # StopNow: a first stop in a compilation
                self.state = None  # consumed by the abandoned iteration
                saved = max(where.saved, 0)
                raise RunInterrupted(saved, where.iterations - saved) from None
            except OSError as e:  # a full disk or an I/O error while logging or saving
                raise write_error(e, where.saved) from e
        if stop is not None and stop.asked:  # a stop during the last iteration: saved, stop
            where.stopped = "interrupted"
        if where.stopped == "interrupted":
            raise RunInterrupted(where.iterations)
        return self.state


# what a run writes into its folder (`overwrite` removes them, and only them, before a new run)
RUN_OUTPUTS = (
    *RUN_RECORDS,
    "learning_curves.png",
    "episode_test0.gif",
    "curve.png",
    "trajectory_test*.png",
    "checkpoints",
    "corrupt_checkpoints",
    "tensorboard",
)


def run_records(run_dir: Path) -> list[str]:
    """The run records (`RUN_RECORDS`, and committed checkpoints) a folder holds."""
    found = [name for name in RUN_RECORDS if (run_dir / name).exists()]
    return found + (["checkpoints/"] if committed_steps(run_dir) else [])


def clear_run_outputs(run_dir: Path) -> None:
    """Remove what a run writes (`RUN_OUTPUTS`) from `run_dir`; other files stay."""
    for pattern in RUN_OUTPUTS:
        for path in run_dir.glob(pattern):
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink()


def _check_fresh(run_dir: Path) -> None:
    """A new run's folder holds no other run: CheckpointError (checkpoints) or RunDirError
    (records) naming the folder and the options otherwise."""
    if committed_steps(run_dir):
        raise CheckpointError(
            f"{run_dir} already holds checkpoints: pass --resume to continue, --overwrite to "
            "replace the run, or choose another --out"
        )
    if run_records(run_dir):
        raise RunDirError(
            f"{run_dir} holds a run's records ({', '.join(run_records(run_dir))}): pass "
            "--overwrite to replace them, or choose another --out"
        )


def open_session(
    cfg: Any,
    out: str | Path,
    resume: bool = False,
    until_budget: bool = False,
    *,
    kind: RunKind = PEARL,
    tensorboard: bool = False,
    overwrite: bool = False,
) -> Session:
    """Open a run folder for training, with a config checked where it was resolved
    (`config.resolve`). Every check before training, in this order: the folder's lock (one
    writer per folder), resume compatibility, writable folders, data and tasks (building the
    trainer) and the memory its state needs, checkpoint restore (falling back past corrupt ones;
    nothing to resume from is an error where iterations were logged), the asked iterations
    against the finished count (not with until_budget: a run that stops on a time budget,
    `training.budget`). A new run (not `resume`) refuses a folder that holds a run's
    records, unless `overwrite` says to replace that run (its outputs are removed once the
    folder is locked). Only then is config.json written and metrics.jsonl cut back to the
    restored iteration. Close the session (`with` or `close()`) once the run's last file is
    written."""
    run_dir = Path(out)
    if resume:
        kind.load_config(run_dir, False)  # a run folder at all, before the lock creates anything
    elif not overwrite:
        _check_fresh(run_dir)  # before the lock file is written into another run's folder
    created = _first_missing(run_dir)  # the folder the lock creates, if any
    lock = RunLock(run_dir, enabled=is_primary())
    try:
        if overwrite and not resume:
            clear_run_outputs(run_dir)
        return _open_locked(cfg, run_dir, resume, until_budget, lock, kind, tensorboard)
    except BaseException:
        if created is not None and lock.held:  # a refused new run leaves no folder behind
            _remove_created(run_dir, created)
        lock.release()
        raise


def _first_missing(folder: Path) -> Path | None:
    """The outermost of `folder` and its parents that does not exist yet (None: it exists)."""
    missing = None
    for p in (folder, *folder.parents):
        if p.exists():
            return missing
        missing = p
    return missing


def _remove_created(run_dir: Path, created: Path) -> None:
    """Remove `run_dir` if it holds nothing but its lock file, then its empty parents up to
    `created`; the lock file goes while still held."""
    with contextlib.suppress(OSError):
        if {p.name for p in run_dir.iterdir()} <= {LOCK_FILE}:
            (run_dir / LOCK_FILE).unlink(missing_ok=True)
            for p in (run_dir, *run_dir.parents):
                p.rmdir()
                if p == created:
                    break


def _open_locked(
    cfg: Any,
    run_dir: Path,
    resume: bool,
    until_budget: bool,
    lock: RunLock,
    kind: RunKind,
    tensorboard: bool,
) -> Session:
    for partial in remove_partial(run_dir) if is_primary() else []:  # a save killed midway
        warn(f"{partial}: removed an unfinished checkpoint (its save was interrupted)")
    if resume:
        field = f"{kind.section}.iterations"
        check_resumable(kind.load_config(run_dir, True), cfg, run_dir, field)
        if not committed_steps(run_dir):
            check_nothing_lost(run_dir)
    else:
        _check_fresh(run_dir)
    new_folder = not (run_dir / "checkpoints").exists()
    check_writable(run_dir)
    trainer = None
    try:
        trainer = kind.make_trainer(cfg)
        kind.check_fits(trainer)
    except BaseException:
        if trainer is not None and hasattr(trainer, "close"):
            trainer.close()
        if new_folder:  # a refused run leaves no empty checkpoints/ behind
            with contextlib.suppress(OSError):
                (run_dir / "checkpoints").rmdir()
        raise
    ckpt = Checkpointer(run_dir, keep=_section(kind, cfg).keep_checkpoints)
    try:
        state = trainer.init_state()
        if resume and ckpt.steps():
            state = ckpt.restore(state)
        done = int(first_local(state.iteration))
        total = _section(kind, cfg).iterations
        if not until_budget and total < done:
            raise CheckpointError(
                f"{run_dir} has finished {done} iterations; --iterations {total} is below that "
                f"(give --iterations {done} or more, or another --out)"
            )
        if kind.network_file:
            save_network(run_dir, trainer.nets)  # what load_policy needs beside policy.msgpack
        rows = read_log(run_dir / LOG_FILE, done)
        if is_primary():  # with several processes, process 0 writes the run's files
            save_config(run_dir, cfg)
            write_log(run_dir / LOG_FILE, rows)
        tb = None
        if tensorboard and is_primary():
            from mpcpearl_jax.training.livelog import TB_DIR, TensorBoardLog

            # a resumed run hides its earlier points from the first iteration redone
            tb = TensorBoardLog(run_dir / TB_DIR, purge_step=done + 1 if done else None)
    except BaseException:
        ckpt.close()
        if hasattr(trainer, "close"):
            trainer.close()
        raise
    return Session(cfg, run_dir, trainer, state, rows, ckpt, lock, kind, tb)


def check_nothing_lost(run_dir: Path) -> None:
    """--resume found no checkpoint: an error naming the folder if metrics.jsonl logs iterations
    (a restart would erase them: never silently); otherwise the run stopped before its first
    iteration and starting at iteration 0 is the exact resume, said in one line."""
    logged = len(read_log(run_dir / LOG_FILE))
    if logged:
        raise CheckpointError(
            f"{run_dir}: nothing to resume: no checkpoint in {run_dir / 'checkpoints'}, but "
            f"{LOG_FILE} logs {logged} iteration(s) that a restart would erase; start over "
            "without --resume (replacing them) or in another --out"
        )
    warn(f"{run_dir}: no checkpoint yet (stopped before its first one); starting at iteration 0")


def train_iterations(
    sess: Session,
    on_row: Callable[[dict[str, Any]], None] | None = None,
    handle_sigint: bool = False,
) -> tuple[Any, dict[str, Any]]:
    """The iterations mode, the training command's rules: `train.iterations` iterations,
    evaluation on the test tasks every `eval_interval` iterations and at the end, checkpoints
    every `checkpoint_interval`; `on_row(row)` sees every row with its evaluation (the command's
    progress bar, `cli.progress`). Prints nothing.

    Returns (state, info), info = {mode, stopped, iterations, saved, lost, train_s,
    first_iteration_s}: stopped is "done", "interrupted" (a stop signal, with handle_sigint: the
    last finished iteration saved) or "diverged: ..."; after those two `state` is None and
    info["error"] is the exception (`RunInterrupted`, `TrainingDiverged`)."""
    from mpcpearl_jax.errors import TrainingDiverged

    cfg, trainer = sess.cfg, sess.trainer
    tc, total = cfg.train, cfg.train.iterations

    def evaluate(row: dict[str, Any], state: TrainState, p: Progress) -> dict[str, Any] | None:
        fields = None
        if p.last or (tc.eval_interval > 0 and p.iterations % tc.eval_interval == 0):
            t0 = time.perf_counter()
            ev = trainer.evaluate(state, online=cfg.online_eval)
            fields = {f"test_{k}": v for k, v in ev.items() if not k.endswith("_per_seed")}
            fields["eval_s"] = time.perf_counter() - t0
        if on_row is not None:
            on_row({**row, **(fields or {})})
        return fields

    info: dict[str, Any] = {"mode": "iterations", "stopped": "done", "lost": 0}
    try:
        state = sess.train(
            until=lambda p: p.iterations >= total,
            on_row=evaluate,
            checkpoint_after=lambda p, _: p.iterations % tc.checkpoint_interval == 0,
            handle_sigint=handle_sigint,
        )
    except RunInterrupted as e:
        info.update(stopped="interrupted", error=e, lost=e.lost)
        state = None
    except TrainingDiverged as e:
        info.update(stopped=f"diverged: {e}", error=e)
        state = None
    p = sess.progress
    info.update(
        # an interrupted run: the iterations a resume continues from
        iterations=info["error"].iteration if info["stopped"] == "interrupted" else p.iterations,
        saved=p.saved,
        train_s=p.train_s,
        first_iteration_s=p.first_iteration_s,
    )
    return state, info


def policy_params(state: TrainState) -> dict:
    """The {policy, encoder} parameters of every seed, on the host (what policy.msgpack holds)."""
    return to_host(acting_params(state.learner.params))
