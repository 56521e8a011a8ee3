"""Checkpoints (orbax) of the full training state under a run folder's checkpoints/<it>/ (the
last few kept; the folder's other files: `mpcpearl_jax.runfolder`).

orbax commits a checkpoint atomically (a temporary folder renamed into place), so a process
killed at any moment leaves the previous one intact. A checkpoint that cannot be restored is
reported and set aside under corrupt_checkpoints/, and the newest intact one is used instead.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

from mpcpearl_jax.errors import CheckpointError, RunDirError
from mpcpearl_jax.notices import warn
from mpcpearl_jax.runfolder import POLICY_FILE, non_finite_leaves, save_params


def check_resumable(
    saved: Any, cfg: Any, run_dir: Path, iterations: str = "train.iterations"
) -> None:
    """Resuming needs the same config except for the number of iterations (the field
    `iterations`, e.g. 'grbal.iterations' for GrBAL) and the fields that do not change results
    (`config.RESULT_NEUTRAL`: the devices, orbax restores onto the new layout; the MPC's worker
    processes)."""
    from mpcpearl_jax.config import RESULT_NEUTRAL

    diff = config_differences(saved, cfg, ignore=(iterations, *RESULT_NEUTRAL))
    if diff:
        raise CheckpointError(
            f"{run_dir}: the saved config differs from the requested one in {diff}; "
            "resume with the same settings (only --iterations may change) or use a new --out"
        )


def config_differences(a: Any, b: Any, ignore: tuple[str, ...] = ()) -> list[str]:
    """The dotted names of the fields in which two configs differ, the fields in `ignore`
    ('section.field' or a top-level field) left out."""
    da, db = (json.loads(json.dumps(c.to_dict())) for c in (a, b))
    for name in ignore:
        section, _, field = name.rpartition(".")
        for d in (da, db):
            (d.get(section, {}) if section else d).pop(field, None)
    return _diff(da, db)


def _diff(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    return [prefix.rstrip(".")] if a != b else []


def committed_steps(run_dir: str | Path) -> list[int]:
    """The iterations of the committed checkpoints in run_dir/checkpoints (orbax renames a
    checkpoint to its step number only once it is complete), oldest first."""
    folder = Path(run_dir) / "checkpoints"
    if not folder.is_dir():
        return []
    return sorted(int(p.name) for p in folder.iterdir() if p.is_dir() and p.name.isdigit())


def remove_partial(run_dir: str | Path) -> list[Path]:
    """Remove the temporary folders a save killed midway left in run_dir/checkpoints (they
    hold nothing a resume could use); returns them."""
    folder = Path(run_dir) / "checkpoints"
    gone = sorted(folder.glob(f"*{TMP_SUFFIX}*")) if folder.is_dir() else []
    for p in gone:
        shutil.rmtree(p, ignore_errors=True)
    return gone


class Checkpointer:
    """Saves and restores the whole TrainState under run_dir/checkpoints."""

    def __init__(self, run_dir: str | Path, keep: int = 3):
        self.run_dir = Path(run_dir).absolute()
        # an interrupted save leaves only a temporary folder, removed here (orbax commits a
        # checkpoint by renaming it into place once complete)
        options = ocp.CheckpointManagerOptions(
            max_to_keep=keep, create=True, cleanup_tmp_directories=True
        )
        self.manager = ocp.CheckpointManager(self.run_dir / "checkpoints", options=options)

    def steps(self) -> list[int]:
        """Committed checkpoint steps, oldest first."""
        return sorted(self.manager.all_steps())

    def save(self, step: int, state, policy_params: dict) -> None:
        """Checkpoint `state` as iteration `step`, then write policy.msgpack. Non-finite
        parameters are refused before anything is written (CheckpointError naming the file). A
        failed write (a full disk, an I/O error) removes the partial checkpoint and raises
        RunDirError naming the folder, the cause and the iteration a resume starts from."""
        primary = jax.process_index() == 0  # every process saves its shards; one writes the rest
        pfile = self.run_dir / POLICY_FILE
        bad = non_finite_leaves(policy_params) if primary else []
        if bad:
            raise CheckpointError(
                f"{pfile}: not saved: non-finite network parameters at iteration {step} (NaN or "
                f"inf, e.g. {bad[0]}); the last good checkpoint is kept"
            )
        try:
            with _quiet_orbax():
                self.manager.save(step, args=ocp.args.StandardSave(state))
                self.manager.wait_until_finished()
        except Exception as e:  # orbax wraps OS errors in ValueError (tensorstore) and others
            self._failed = True
            self._discard_partial()
            raise _save_error(self.run_dir / "checkpoints" / str(step), e, self.steps()) from e
        if primary:
            try:
                save_params(pfile, policy_params)
            except OSError as e:
                self._failed = True
                raise _save_error(pfile, e, self.steps()) from e

    def _discard_partial(self) -> None:
        """Remove the temporary folders of a save that failed (orbax renames a checkpoint into
        place only once complete, so they hold nothing a resume could use)."""
        folder = self.run_dir / "checkpoints"
        for p in folder.glob(f"*{TMP_SUFFIX}*") if folder.is_dir() else []:
            shutil.rmtree(p, ignore_errors=True)
        with contextlib.suppress(Exception):
            self.manager.reload()

    def restore(
        self, template, step: int | None = None, report: Callable[[str], None] | None = None
    ):
        """The state saved at `step`; by default the newest checkpoint that restores. A newer one
        that does not is reported (`report`, default: a line on stderr) and moved to
        corrupt_checkpoints/. Returns the state; the step restored is `self.restored_step`."""
        if step is not None:
            state = self._restore_step(template, step)
            self.restored_step = step
            return state
        steps = self.steps()
        if not steps:
            raise CheckpointError(f"{self.run_dir}: no checkpoint to resume from")
        report = report or warn
        errors = []
        for i, s in enumerate(reversed(steps)):
            try:
                state = self._restore_step(template, s)
            except CheckpointError as e:
                errors.append(str(e))
                moved = self._set_aside(s)
                older = steps[-i - 2] if i + 1 < len(steps) else None
                then = f"falling back to iteration {older}" if older is not None else "none left"
                report(f"warning: {e}; moved to {moved}; {then}")
                continue
            self.restored_step = s
            return state
        raise CheckpointError(
            f"{self.run_dir}/checkpoints: no intact checkpoint (tried {steps[::-1]}); "
            "start again with a new --out"
        )

    def _restore_step(self, template, step: int):
        abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, template)
        where = f"{self.run_dir}/checkpoints/{step}"
        try:
            state = self.manager.restore(step, args=ocp.args.StandardRestore(abstract))
        except Exception as e:  # orbax raises many types for corrupt or mismatched trees
            first = (str(e).strip().splitlines() or [""])[0].split(" See full TensorStore")[0]
            raise CheckpointError(
                f"{where}: cannot restore the training state "
                f"(corrupt, or saved with a different configuration): {type(e).__name__}: "
                f"{first[:200]}"
            ) from e
        it = getattr(state, "iteration", None)
        if it is not None and not bool(jnp.all(jnp.asarray(it) == step)):
            raise CheckpointError(f"{where}: cannot restore: it holds iteration {it}, not {step}")
        for leaf in jax.tree_util.tree_leaves(getattr(state, "learner", None)):
            if jnp.issubdtype(leaf.dtype, jnp.floating) and not bool(jnp.all(jnp.isfinite(leaf))):
                raise CheckpointError(f"{where}: cannot restore: non-finite network parameters")
        return state

    def _set_aside(self, step: int) -> Path:
        """Move a checkpoint that does not restore out of the manager's folder."""
        src = self.run_dir / "checkpoints" / str(step)
        dst_dir = self.run_dir / "corrupt_checkpoints"
        dst_dir.mkdir(exist_ok=True)
        dst, n = dst_dir / str(step), 1
        while dst.exists():
            dst, n = dst_dir / f"{step}.{n}", n + 1
        shutil.move(str(src), str(dst))
        self.manager.reload()
        return dst

    def close(self) -> None:
        try:
            with _quiet_orbax():
                self.manager.close()
        except Exception:
            if not getattr(self, "_failed", False):
                raise  # after a failed save the error has been reported once already


TMP_SUFFIX = ".orbax-checkpoint-tmp"  # orbax's name for a checkpoint not yet committed


@contextlib.contextmanager
def _quiet_orbax() -> Iterator[None]:
    """orbax logs every failure of its writer threads with a traceback before raising it, and
    after a failed write (a full disk) the writes still under way end on a closed event loop,
    each printing `RuntimeError: Event loop is closed`; the caller reports the one failure as one
    line instead. After a failure those closed-loop errors stay silenced (the writer threads
    outlive the call)."""
    log = logging.getLogger("absl")
    level, hooks = log.level, (sys.excepthook, sys.unraisablehook)
    log.setLevel(logging.CRITICAL)
    sys.excepthook = _skip_closed_loop(sys.excepthook)
    sys.unraisablehook = _skip_closed_loop_unraisable(sys.unraisablehook)
    try:
        yield
    except BaseException:
        log.setLevel(level)
        raise
    log.setLevel(level)
    sys.excepthook, sys.unraisablehook = hooks


def _closed_loop(value: BaseException | None) -> bool:
    return isinstance(value, RuntimeError) and str(value) == "Event loop is closed"


def _skip_closed_loop(hook: Callable) -> Callable:
    def excepthook(kind, value, tb):
        if not _closed_loop(value):
            hook(kind, value, tb)

    return excepthook


def _skip_closed_loop_unraisable(hook: Callable) -> Callable:
    def unraisablehook(unraisable):
        if not _closed_loop(unraisable.exc_value):
            hook(unraisable)

    return unraisablehook


def _cause(e: BaseException) -> str:
    """The operating system's words for an error (orbax and tensorstore wrap them), else the
    first line of the message."""
    seen: BaseException | None = e
    while seen is not None:
        if isinstance(seen, OSError) and seen.strerror:
            return seen.strerror
        code = re.search(r"os_error_code='?(\d+)", str(seen))
        if code:
            return os.strerror(int(code.group(1)))
        seen = seen.__cause__ or seen.__context__
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def resume_hint(saved: int) -> str:
    """What to do once the cause of a failed write is fixed (saved: the newest checkpoint's
    iteration, -1: none)."""
    if saved >= 0:
        return f"--resume continues from iteration {saved} once the cause is fixed"
    return "no checkpoint was saved yet: once the cause is fixed, start again with --overwrite"


def _save_error(where: Path, e: BaseException, steps: list[int]) -> RunDirError:
    hint = resume_hint(steps[-1] if steps else -1)
    return RunDirError(f"{where}: cannot save ({_cause(e)}); {hint}")
