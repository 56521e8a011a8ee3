"""Run an experiment: train with checkpoints and a metrics log, evaluate, write figures and the
results table. Used by `python -m experiments.restaurant` and `python -m experiments.sidewalk`.

Resume is exact: everything that shapes the rest of a run is in the checkpointed TrainState or
rebuilt deterministically from the config, so a run stopped at any moment (kill -9, Ctrl-C, power
loss) and resumed ends bit-identical to one never stopped. metrics.jsonl is appended one whole line
at a time; rows beyond the restored checkpoint are recomputed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.config import ExperimentConfig, validate
from mpcpearl_jax.distributed import first_local, is_primary, to_host
from mpcpearl_jax.errors import CheckpointError, RunDirError
from mpcpearl_jax.evaluation.report import PAPER, plot_learning_curves, results_table
from mpcpearl_jax.pearl.learner import acting_params
from mpcpearl_jax.training.checkpoint import (
    Checkpointer,
    atomic_write,
    check_resumable,
    load_config,
    save_config,
    save_network,
    write_json,
)
from mpcpearl_jax.training.loop import Progress, train_loop
from mpcpearl_jax.training.machine import machine_info
from mpcpearl_jax.training.resources import check_state_fits
from mpcpearl_jax.training.runlock import RunLock
from mpcpearl_jax.training.trainer import IterationAbandoned, Trainer, TrainState

LOG_FILE = "metrics.jsonl"


class RunInterrupted(Exception):
    """Training stopped on Ctrl-C (SIGINT); `iteration` iterations are saved and resumable."""

    def __init__(self, iteration: int, lost: int = 0):
        self.iteration, self.lost = iteration, lost
        span = f"{iteration + 1}-{iteration + lost}" if lost > 1 else f"{iteration + 1}"
        extra = f" (iteration(s) {span}, finished after the last checkpoint, are redone)"
        extra = extra if lost else ""
        super().__init__(f"interrupted at iteration {iteration}; continue with --resume{extra}")


def _warn(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def read_log(path: Path, upto: int = 10**9, report: Callable[[str], None] = _warn) -> list[dict]:
    """Rows of metrics.jsonl with iteration <= upto. A torn last line (a process killed while
    appending it) is dropped with a warning naming the file; a bad line elsewhere is an error."""
    if not path.is_file():
        return []
    lines = path.read_bytes().split(b"\n")
    rows = []
    for i, raw in enumerate(lines):
        if not raw.strip():
            continue
        try:
            rows.append(json.loads(raw))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            if any(x.strip() for x in lines[i + 1 :]):
                raise CheckpointError(f"{path}: line {i + 1} is not JSON ({e})") from e
            report(f"warning: {path}: dropped a torn last line (line {i + 1}, {len(raw)} bytes)")
    return [r for r in rows if r.get("iteration", 0) <= upto]


def _write_log(path: Path, rows: list[dict]) -> None:
    atomic_write(path, "".join(json.dumps(r) + "\n" for r in rows))


def append_log(path: Path, row: dict) -> None:
    """Append one line with a single write on an O_APPEND descriptor: a crash leaves at most a
    torn last line (dropped on resume), never a mixed one."""
    data = (json.dumps(row) + "\n").encode()
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
        finally:
            os.close(fd)
    except OSError as e:  # e.g. a full disk: name the file
        raise OSError(e.errno, e.strerror or str(e), str(path)) from e


def write_error(e: OSError, saved: int) -> RunDirError:
    """A failed write during training (a full disk, an I/O error) as one line: the file, the
    cause, and the iteration a resume starts from (saved: the newest checkpoint, -1: none)."""
    then = (
        f"--resume continues from iteration {saved}" if saved >= 0 else "no checkpoint is saved yet"
    )
    where = e.filename or "the run folder"
    return RunDirError(f"{where}: cannot write ({e.strerror or e}); {then} once the cause is fixed")


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
            raise RunDirError(
                f"{d}: not writable ({e.strerror or type(e).__name__}); fix its permissions "
                "or choose another --out"
            ) from e


def _eval_row(trainer: Trainer, state: TrainState) -> dict[str, Any]:
    online = trainer.cfg.online_eval
    ev = trainer.evaluate(state, online=online)
    ev.pop("_raw")
    return {f"test_{k}": v for k, v in ev.items() if not k.endswith("_per_seed")}


@dataclasses.dataclass
class Session:
    """A run ready to train: every check passed, state restored, config.json and the log written."""

    cfg: ExperimentConfig
    run_dir: Path
    trainer: Trainer
    ckpt: Checkpointer
    state: TrainState
    rows: list[dict]
    done: int
    saved: int  # the iteration of the newest checkpoint (-1: none)
    lock: (
        RunLock  # this process writes run_dir (mpcpearl_jax.training.runlock); release() when done
    )


def prepare(
    cfg: ExperimentConfig, out: str | Path, resume: bool = False, until_budget: bool = False
) -> Session:
    """Every check before training, in this order: config (MPC and env overrides), the run
    directory's lock (one writer per folder), resume compatibility, writable folders, data and
    tasks (building the Trainer), checkpoint restore (falling back past corrupt ones; nothing to
    resume from is an error where iterations were logged), --iterations against the finished
    count (not with until_budget: a run that stops on a time budget, `experiments.learning`).
    Only then is config.json written and metrics.jsonl cut back to the restored iteration. The
    session holds the lock: `sess.lock.release()` once the run's last file is written."""
    run_dir = Path(out)
    validate(cfg)
    if resume:
        load_config(run_dir)  # a run folder at all, before the lock creates anything
    lock = RunLock(run_dir, enabled=is_primary())
    try:
        return _prepare_locked(cfg, run_dir, resume, until_budget, lock)
    except BaseException:
        lock.release()
        raise


def _prepare_locked(
    cfg: ExperimentConfig, run_dir: Path, resume: bool, until_budget: bool, lock: RunLock
) -> Session:
    if resume:
        check_resumable(load_config(run_dir, resume=True), cfg, run_dir)
        folder = run_dir / "checkpoints"
        if not (folder.is_dir() and any(p.name.isdigit() for p in folder.iterdir())):
            check_nothing_lost(run_dir)
    elif (run_dir / "checkpoints").is_dir() and any((run_dir / "checkpoints").iterdir()):
        raise CheckpointError(
            f"{run_dir} already holds checkpoints: pass --resume to continue "
            "or choose another --out"
        )
    new_folder = not (run_dir / "checkpoints").exists()
    check_writable(run_dir)
    try:
        trainer = Trainer(cfg)
        check_state_fits(  # before anything is allocated
            trainer.init_state,
            "the training state (replay buffers, networks)",
            "train.rl_capacity, train.mpc_buffer_capacity, the training tasks or the seeds",
        )
    except BaseException:
        if new_folder:  # a refused run leaves no empty checkpoints/ behind
            with contextlib.suppress(OSError):
                (run_dir / "checkpoints").rmdir()
        raise
    ckpt = Checkpointer(run_dir, keep=cfg.train.keep_checkpoints)
    try:
        state = trainer.init_state()
        saved = -1
        if resume and ckpt.steps():
            state = ckpt.restore(state)
            saved = ckpt.restored_step
        done = int(first_local(state.iteration))
        if not until_budget and cfg.train.iterations < done:
            raise CheckpointError(
                f"{run_dir} has finished {done} iterations; --iterations {cfg.train.iterations} "
                f"is below that (give --iterations {done} or more, or another --out)"
            )
    except BaseException:
        ckpt.close()
        raise
    save_network(run_dir, trainer.nets)  # what load_policy needs beside policy.msgpack
    log_path = run_dir / LOG_FILE
    rows = read_log(log_path, done)
    if is_primary():  # with several processes, process 0 writes the run's files
        save_config(run_dir, cfg)
        _write_log(log_path, rows)
    return Session(cfg, run_dir, trainer, ckpt, state, rows, done, saved, lock)


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
    _warn(f"{run_dir}: no checkpoint yet (stopped before its first one); starting at iteration 0")


@contextlib.contextmanager
def _sigint_flag(enabled: bool):
    """A stop flag set by the first Ctrl-C (SIGINT); a second one stops at once."""
    flag = {"stop": False}
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield None
        return

    def handler(signum, frame):
        if flag["stop"]:
            raise KeyboardInterrupt
        flag["stop"] = True
        _warn("\nCtrl-C: stopping at the next phase boundary (Ctrl-C again: stop at once)")

    old = signal.signal(signal.SIGINT, handler)
    try:
        yield lambda: flag["stop"]
    finally:
        signal.signal(signal.SIGINT, old)


def train(
    cfg: ExperimentConfig,
    out: str | Path,
    resume: bool = False,
    progress: bool = True,
    handle_sigint: bool = False,
    tensorboard: bool = False,
) -> tuple[Trainer, TrainState]:
    """Train `cfg` into `out` (checkpoints, config.json, metrics.jsonl); -> (trainer, state).

    With handle_sigint, Ctrl-C abandons the current phase at its next boundary (at most one update
    chunk, ~10 s), saves a checkpoint of the last finished iteration if it is still in memory,
    and raises RunInterrupted. With tensorboard, every metrics row also goes to out/tensorboard
    (`mpcpearl_jax.training.livelog`)."""
    sess = prepare(cfg, out, resume)
    try:
        return train_session(sess, progress, handle_sigint, tensorboard)
    finally:
        sess.lock.release()


def train_session(
    sess: Session, progress: bool = True, handle_sigint: bool = False, tensorboard: bool = False
) -> tuple[Trainer, TrainState]:
    """Train a prepared session (see `train`)."""
    tb = None
    progress = progress and is_primary()
    # a resumed run hides its earlier points from the first iteration redone
    if tensorboard and is_primary():
        from mpcpearl_jax.training.livelog import TB_DIR, TensorBoardLog

        tb = TensorBoardLog(sess.run_dir / TB_DIR, purge_step=sess.done + 1 if sess.done else None)
    with _sigint_flag(handle_sigint) as stop:
        try:
            return sess.trainer, _loop(sess, progress, stop, tb)
        finally:
            sess.ckpt.close()
            if tb is not None:
                tb.close()


def _loop(sess: Session, progress: bool, stop: Callable[[], bool] | None, tb=None) -> TrainState:
    """`loop.train_loop` for a number of iterations: evaluation every `eval_interval` iterations
    and at the end, checkpoints every `checkpoint_interval`; Ctrl-C -> RunInterrupted."""
    cfg, trainer, ckpt = sess.cfg, sess.trainer, sess.ckpt
    tc, log_path, total = cfg.train, sess.run_dir / LOG_FILE, cfg.train.iterations
    # a resumed run's clocks go on from its last kept iteration row: train_s and wall_s are over
    # the run's lifetime (metrics.jsonl), not over this process
    last = next((r for r in reversed(sess.rows) if "train_s" in r), {})
    where = Progress(
        iterations=sess.done,
        saved=sess.saved,
        train_s=float(last.get("train_s", 0.0)),
        wall_s0=float(last.get("wall_s", 0.0)),
    )
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            total=total,
            initial=sess.done,
            desc=f"{cfg.env} eps={tc.eps}",
            dynamic_ncols=True,
        )

    def evaluate(state: TrainState, p: Progress) -> dict[str, Any]:
        t0 = time.perf_counter()
        row = _eval_row(trainer, state)
        return {**row, "eval_s": time.perf_counter() - t0}

    def on_row(row: dict[str, Any]) -> None:
        sess.rows.append(row)
        if is_primary():
            append_log(log_path, row)
        if tb is not None:
            tb.write(row)
        if bar is not None:
            post = {"ret": f"{row['train_return']:.0f}", "mpc": f"{row['train_mpc_share']:.2f}"}
            if "test_SR" in row:
                post.update(SR=f"{row['test_SR']:.2f}", CFR=f"{row['test_CFR']:.2f}")
            bar.set_postfix(post)
            bar.update(1)

    try:
        state = train_loop(
            trainer,
            sess.state,
            where,
            until=lambda p: p.iterations >= total,
            save=lambda it, s: ckpt.save(it, s, policy_params(s)),
            on_row=on_row,
            evaluate_after=lambda p: tc.eval_interval > 0 and p.iterations % tc.eval_interval == 0,
            evaluate=evaluate,
            checkpoint_after=lambda p, _: p.iterations % tc.checkpoint_interval == 0,
            stop=stop,
        )
    except IterationAbandoned:
        saved = max(where.saved, 0)
        raise RunInterrupted(saved, where.iterations - saved) from None
    except OSError as e:  # a full disk or an I/O error while logging
        raise write_error(e, where.saved) from e
    finally:
        if bar is not None:
            bar.close()
    if where.stopped == "interrupted":
        raise RunInterrupted(where.iterations)
    return state


def policy_params(state: TrainState) -> dict:
    """The {policy, encoder} parameters of every seed, on the host (what policy.msgpack holds)."""
    return to_host(acting_params(state.learner.params))


def final_evaluation(
    trainer: Trainer, state: TrainState, out: str | Path, label: str
) -> dict[str, Any]:
    """Evaluate on test (adaptation and online) and OOD tasks; save results.json + figures."""
    from mpcpearl_jax.envs import tasks_for

    run_dir = Path(out)
    results: dict[str, Any] = {
        "label": label,
        "env": trainer.cfg.env,
        "config": trainer.cfg.to_dict(),
    }
    adapt = trainer.evaluate(state)
    online = trainer.evaluate(state, online=True)
    raw = adapt.pop("_raw")
    online.pop("_raw")
    results["test_adapt"] = adapt
    results["test_online"] = online
    try:  # the OOD split of the run's own task source (its task options: e.g. the scenarios)
        ood = tasks_for(trainer.cfg, "ood", config=trainer.env.config)
        res = trainer.evaluate(state, tasks=ood)
        res.pop("_raw")
        results["ood_adapt"] = res
    except (ValueError, FileNotFoundError) as e:  # no OOD split (or no OOD scenario file)
        results["ood_adapt"] = {"skipped": str(e)}
    results["paper"] = PAPER.get(trainer.cfg.env, {})
    results["machine"] = machine_info()  # run times depend on it (CPU model, cores, versions)
    if not is_primary():  # every process evaluates its seeds; process 0 writes
        return results
    write_json(run_dir / "results.json", results)
    print(results_table(results))
    plot_learning_curves([(label, read_log(run_dir / LOG_FILE))], run_dir / "learning_curves.png")
    _trajectory_figure(trainer, raw, run_dir)
    _episode_gif(trainer, raw, run_dir, label)
    return results


def _episode_gif(trainer: Trainer, raw: dict, run_dir: Path, label: str) -> Path:
    """episode_test0.gif: seed 0's evaluated episode on test task 0
    (`mpcpearl_jax.evaluation.animate`)."""
    from mpcpearl_jax.evaluation.animate import animate_result

    title = f"{label} (seed 0), {trainer.cfg.env} test task 0"
    path = run_dir / "episode_test0.gif"
    return animate_result(path, raw, trainer.test_tasks, trainer.env.config, title=title)


def _trajectory_figure(trainer: Trainer, raw: dict, run_dir: Path, n: int = 4) -> None:
    """The first n test tasks with seed 0's evaluated episode (paper-style figures, in the
    family's style: its registered viewer)."""
    from mpcpearl_jax.envs import save_trajectory

    for i in range(min(n, int(trainer.test_tasks.start.shape[0]))):
        task = jax.tree_util.tree_map(lambda x, i=i: x[i], trainer.test_tasks)
        pos = np.asarray(raw["position"][0, i])
        col = np.asarray(raw["collision"][0, i])
        path = run_dir / f"trajectory_test{i}.png"
        robots = {"policy (seed 0)": (pos, col)}
        save_trajectory(trainer.cfg.env, path, task, robots, trainer.env.config)
