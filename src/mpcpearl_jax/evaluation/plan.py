"""The pieces of `mpcpearl_jax.evaluate` below the run loading: the evaluated tasks of a split
(task seed, the paper's scenarios, a task selection, figure tasks, a crowd perturbation), the MPC
settings, the output folder, the controller run on the tasks and the record it gives
(results.json), and its trajectory figures.

A bad argument is an `EvaluationError` (a ValueError) in one line naming the argument. Its
`template` writes each argument's name as `{name}`: `str(error)` spells them as `evaluate`'s
keyword arguments, `error.spelled(names)` in another vocabulary (the command line's flags).
"""

from __future__ import annotations

import contextlib
import re
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.envs import tasks_for
from mpcpearl_jax.envs.perturb import parse_perturbation, perturb_tasks
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.evaluation.runners import (
    Setup,
    run_gp_mpc,
    run_policy,
    run_policy_mpc,
)
from mpcpearl_jax.evaluation.scoring import failures, per_task_metrics, pooled
from mpcpearl_jax.runfolder import RUN_RECORDS
from mpcpearl_jax.validate import unwritable_folder

FIGURES = 4  # default number of tasks with a figure (and a GIF with animate)

# the arguments an EvaluationError may name ({name} in its template)
ARGUMENTS = (
    "run",
    "controller",
    "env",
    "split",
    "tasks",
    "task_seed",
    "task_seeds",
    "scenarios",
    "data",
    "perturb",
    "episodes",
    "online",
    "seed_index",
    "shield",
    "eps",
    "preset",
    "mpc",
    "eval_seed",
    "figures",
    "animate",
    "out",
    "overwrite",
)
_NAME = re.compile(r"\{(" + "|".join(ARGUMENTS) + r")\}")
_LIBRARY_SPELLING = {"overwrite": "overwrite=True"}


class EvaluationError(ValueError):
    """A bad argument of `mpcpearl_jax.evaluate` (or an input file it names), in one line. The
    `template` names each argument as `{name}` (a name of `ARGUMENTS`); `str()` spells them as
    keyword arguments, `spelled` with other names (e.g. a command line's flags)."""

    def __init__(self, template: str) -> None:
        self.template = template
        super().__init__(self.spelled())

    def spelled(self, spell: Callable[[str], str] | None = None) -> str:
        """The message with each argument named by `spell(name)` (default: its keyword)."""
        name = spell or (lambda n: _LIBRARY_SPELLING.get(n, n))
        return _NAME.sub(lambda m: name(m.group(1)), self.template)


# ----------------------------------------------------------------------------- task selections
_FORMS = "expected numbers like 0,3,5, 0-3 (inclusive) or 0:4 (4 excluded)"


def _spans(text: str, arg: str, n: int | None = None) -> list[tuple[int, int]]:
    """'0,3,5' | '0-3' (inclusive) | '0:4' (STOP excluded; either end may be left out, START 0
    and STOP `n`) | a mix -> its inclusive (lo, hi) spans, sorted and merged, never expanded (a
    span may be billions long). EvaluationError naming `arg` for a malformed, reversed or empty
    range and for nothing at all."""
    spans: list[tuple[int, int]] = []
    for part in text.split(","):
        try:
            if ":" in part:
                a, _, b = part.partition(":")
                lo = int(a) if a.strip() else 0
                if not b.strip() and n is None:
                    raise ValueError(part)
                stop = int(b) if b.strip() else n
                assert stop is not None
                if lo < 0 or stop <= lo:
                    raise EvaluationError(
                        f"{{{arg}}} {text!r}: the range {part.strip()} is empty or negative "
                        "(give START:STOP, 0 <= START < STOP)"
                    )
                lo, hi = lo, stop - 1
            else:
                a, dash, b = part.partition("-")
                lo, hi = int(a), (int(b) if dash else int(a))
        except EvaluationError:
            raise
        except ValueError:
            raise EvaluationError(f"{{{arg}}} {text!r}: {_FORMS}") from None
        if hi < lo:
            raise EvaluationError(
                f"{{{arg}}} {text!r}: the range {part.strip()} is reversed (give A-B, A <= B)"
            )
        spans.append((lo, hi))
    merged: list[tuple[int, int]] = []
    for lo, hi in sorted(spans):
        if merged and lo <= merged[-1][1] + 1:
            merged[-1] = (merged[-1][0], max(merged[-1][1], hi))
        else:
            merged.append((lo, hi))
    return merged


def _count(spans: list[tuple[int, int]]) -> int:
    return sum(hi - lo + 1 for lo, hi in spans)


def _text(spec: str | Iterable[int]) -> str:
    """A selection given as integers (a list, a range) written as the text form."""
    if isinstance(spec, str):
        return spec
    items = list(spec)
    if not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in items):
        raise TypeError(f"expected integers, got {items[:5]!r}")
    return ",".join(str(int(i)) for i in items) or "none"


def parse_ranges(
    spec: str | Iterable[int],
    arg: str,
    cap: int | None = None,
    unit: str = "values",
    hint: str = "",
) -> set[int]:
    """The integers of '0,3,5' | '0-3' | '0:4' | a mix (`_spans`), or of a sequence of them; with
    `cap`, EvaluationError naming `arg` when there are more than `cap` of them (`unit`, then
    `hint`), checked before anything is expanded."""
    text = _text(spec)
    spans = _spans(text, arg)
    n = _count(spans)
    if cap is not None and n > cap:
        raise EvaluationError(f"{{{arg}}} {text}: {n} {unit}; at most {cap}{hint}")
    return {i for lo, hi in spans for i in range(lo, hi + 1)}


def parse_indices(spec: str | Iterable[int], n: int, arg: str) -> list[int]:
    """'all' | 'none' | '0,3,5' | '0-3' (inclusive) | '0:4' (4 excluded) | a mix, or a sequence of
    integers -> sorted unique indices < n; EvaluationError naming `arg` otherwise."""
    text = _text(spec).strip().lower()
    if text == "all":
        return list(range(n))
    if text in ("none", ""):
        return []
    spans = _spans(text, arg, n)
    beyond = [(max(lo, n), hi) for lo, hi in spans if hi >= n]  # checked before expanding
    if beyond:
        count = _count(beyond)
        first = [i for lo, hi in beyond for i in range(lo, min(hi, lo + 5) + 1)][:5]
        shown = first if count <= 5 else f"{first[:3]} and {count - 3} more"
        raise EvaluationError(
            f"{{{arg}}}: task(s) {shown} out of range; the split has {n} tasks (0-{n - 1})"
        )
    return sorted(i for lo, hi in spans for i in range(lo, hi + 1))


# ---------------------------------------------------------------------------- other arguments
def check_eval_seed(seed: int) -> None:
    """EvaluationError unless `seed` makes a PRNG key (an integer that fits 64 bits)."""
    try:
        jax.random.PRNGKey(seed)
    except (OverflowError, ValueError, TypeError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise EvaluationError(f"{{eval_seed}} {seed}: not a PRNG seed ({first})") from None


def check_out(out: Path, overwrite: bool = False) -> None:
    """Create the output folder and prove it writable before any work (a probe file written and
    removed); EvaluationError naming it otherwise. A run's folder (it holds a run's records) is
    never an output folder, and an earlier evaluation's results.json is replaced only with
    `overwrite`."""
    records = [name for name in RUN_RECORDS[:4] if (out / name).exists()]
    if records:
        raise EvaluationError(
            f"{{out}} {out}: a run's folder (it holds {', '.join(records)}); an evaluation never "
            f"writes over a run's records: choose another {{out}}, e.g. {out / 'eval' / 'NAME'}"
        )
    if (out / "results.json").exists() and not overwrite:
        raise EvaluationError(
            f"{{out}} {out}: holds an earlier evaluation's results.json; pass {{overwrite}} to "
            "replace it, or choose another {out}"
        )
    why = unwritable_folder(out)
    if why is not None:
        raise EvaluationError(f"{{out}} {out}: not writable ({why}); choose another {{out}}")


def mpc_settings(
    env_name: str,
    base: Mapping[str, Any] | None,
    preset_name: str | None = None,
    changes: Mapping[str, Any] | Sequence[str] = (),
) -> dict:
    """The MPCConfig fields of an evaluation: `base` (a run's MPC, or the family's defaults when
    None), or with `preset_name` that preset's MPC under the family's defaults; then `changes`
    ('FIELD=VALUE' strings read by each field's type, or a mapping of typed values) on top,
    checked; EvaluationError naming the preset or `mpc` in one line."""
    from mpcpearl_jax.config import mpc_config, parse_override, preset
    from mpcpearl_jax.envs import mpc_defaults
    from mpcpearl_jax.mpc import MPCConfig

    if preset_name is not None:
        try:
            out = preset(preset_name).mpc.replace(**mpc_defaults(env_name)).to_dict()
        except ConfigError as e:
            raise EvaluationError(f"{{preset}}: {e}") from e
    else:
        out = dict(base) if base is not None else mpc_defaults(env_name)
    try:
        if isinstance(changes, Mapping):
            out.update(changes)
        else:
            for item in changes:
                _, field, value = parse_override(item, {"": MPCConfig})
                out[field] = value
    except ConfigError as e:
        raise EvaluationError(str(e)) from e
    try:
        mpc_config(out)  # the one check of MPCConfig fields and values
    except ValueError as e:
        raise EvaluationError(f"{{mpc}}: {e}") from e
    return out


# ------------------------------------------------------------------------------ task sets
def task_setup(
    cfg: Any,
    env: Any,
    env_name: str,
    data: str | None,
    split: str,
    *,
    task_seed: int | None = None,
    several_seeds: bool = False,
    scenarios: Path | None = None,
    tasks: str | Sequence[int] = "all",
    figures: str | Sequence[int] | None = None,
    perturb: str = "none",
):
    """The evaluated tasks of a split for a run config `cfg` (None: `env_name`'s defaults), as
    the arguments name them (`task_seed`, whether there are `several_seeds`, `scenarios`,
    `tasks`, `figures`, `perturb`): (task seed, scenario source, tasks, task ids, figure ids,
    perturbation, the split's number of tasks)."""
    seed = task_seed if task_seed is not None else (cfg.task_seed if cfg else 0)
    source = (cfg or ExperimentConfig(env=env_name)).replace(data=data)
    given_seed = task_seed is not None or several_seeds
    options = scenario_source(cfg, env_name, source.task_options, split, scenarios, given_seed)
    if options is not None:  # the paper's scenarios, in place of the run's task source
        source = source.replace(data=None, task_options=options)
    try:
        all_tasks = tasks_for(source, split, config=env.config, seed=seed)
    except (ValueError, TypeError, OSError) as e:
        if isinstance(e, OSError) and options is None:
            raise
        raise EvaluationError(f"{env_name} {{split}} {split}: {e}") from e
    n = all_tasks.num_tasks
    task_ids = parse_indices(tasks, n, "tasks")
    if not task_ids:
        raise EvaluationError("{tasks}: no task selected")
    if figures is None:
        figure_ids = task_ids[:FIGURES]
    else:
        figure_ids = parse_indices(figures, n, "figures")
        missing = sorted(set(figure_ids) - set(task_ids))
        if missing:
            raise EvaluationError(
                f"{{figures}}: task(s) {missing} are not evaluated (see {{tasks}})"
            )
    chosen = jax.tree_util.tree_map(lambda x: x[np.asarray(task_ids)], all_tasks)
    try:
        perturbation = parse_perturbation(perturb)
    except ValueError as e:
        text, flag = str(e), "--perturb"  # the parser's messages name the command line's flag
        raise EvaluationError(
            "{perturb}" + text[len(flag) :] if text.startswith(flag) else text
        ) from e
    return (
        seed,
        options,
        perturb_tasks(chosen, perturbation),
        task_ids,
        figure_ids,
        perturbation,
        n,
    )


def default_out(
    run: Path, name: str, split: str, online: bool, scenarios: Any, perturbation: Any
) -> Path:
    """The default output folder of an evaluation of `run`: RUN/eval/NAME-SPLIT[-online]."""
    split_name = f"scenarios-{split}" if scenarios is not None else split
    split_name += perturbation.folder_suffix
    return run / "eval" / (f"{name}-{split_name}" + ("-online" if online else ""))


def scenario_source(
    cfg: Any,
    env_name: str,
    task_options: dict,
    split: str,
    scenarios: Path | None = None,
    given_seed: bool = False,
) -> dict | None:
    """The task options of the paper's scenarios when they are the task source (`scenarios`, or
    the run trained on them), else None. A run that trained on every training scenario is not
    scored on the val split (its tasks 150-179 were training tasks)."""
    from mpcpearl_jax.envs.restaurant.scenarios import check_val_split, scenario_options

    if scenarios is None and not task_options.get("scenarios"):
        return None
    if env_name != "restaurant":
        raise EvaluationError(
            f"{{scenarios}}: the paper's scenarios are restaurant tasks, not {env_name}"
        )
    if given_seed:
        raise EvaluationError("{task_seed}(s): the paper's scenarios are one fixed set of tasks")
    trained = dict(cfg.task_options) if cfg else {}
    try:
        if scenarios is not None:
            out = scenario_options(scenarios)
        else:  # the run's own scenarios: the same files it recorded
            out = {k: v for k, v in task_options.items() if k in ("scenarios", "scenario_sha256")}
        check_val_split(trained, split)
    except (ValueError, OSError) as e:
        raise EvaluationError(f"{{scenarios}}: {e}") from e
    return out


# --------------------------------------------------------------------------- running, records
def write_figures(s: Setup, result: dict, animate: bool) -> list[Path]:
    """A trajectory PNG (and a GIF with animate) of the first evaluated seed on each figure
    task, in the family's style (its registered viewer)."""
    from mpcpearl_jax.envs import save_trajectory
    from mpcpearl_jax.evaluation import animate as anim_lib

    written = []
    who = f"seed {s.seed_ids[0]}" if s.seed_ids else s.label
    for t in s.figure_ids:
        j = s.task_ids.index(t)
        task = jax.tree_util.tree_map(lambda x, j=j: np.asarray(x)[j], s.tasks)
        pos, col = np.asarray(result["position"][0, j]), np.asarray(result["collision"][0, j])
        title = f"{s.label}{f' ({who})' if s.seed_ids else ''}, {s.env_name} {s.split} task {t}"
        png = s.out / f"trajectory_{s.split}{t}.png"
        with _names_the_file(png, s.out):
            save_trajectory(s.env_name, png, task, {who: (pos, col)}, s.env_config, title)
        written.append(png)
        if animate:
            path = s.out / f"episode_{s.split}{t}.gif"
            with _names_the_file(path, s.out):
                gif = anim_lib.animate_result(path, result, s.tasks, s.env_config, j, 0, title)
            written.append(gif)
    return written


@contextlib.contextmanager
def _names_the_file(path: Path, out: Path):
    """An OSError while writing the figure `path` (a full disk: "[Errno 28] No space left on
    device", naming no file) raised again naming it, and saying that results.json was written
    first; a partly written figure is removed."""
    try:
        yield
    except OSError as e:
        with contextlib.suppress(OSError):
            path.unlink(missing_ok=True)
        why = e.strerror or str(e) or type(e).__name__
        raise OSError(
            e.errno,
            f"cannot write ({why}); {out / 'results.json'} was written, this figure was not",
            str(path),
        ) from e


def run_setup(
    s: Setup, eval_seed: int, episodes: int | None = None, online: bool = False
) -> tuple[dict, dict, dict | None]:
    """Run the controller on the tasks with the PRNG seed `eval_seed` (`episodes` adaptation
    episodes, None: the run's; or `online`); -> (record for results.json, raw arrays [S, N,
    ...], the MPC's statistics or None)."""
    from mpcpearl_jax.evaluation import evaluate as eval_lib

    key = jax.random.PRNGKey(eval_seed)
    stats = None
    t0 = time.perf_counter()
    if s.controller == "policy":
        episodes = s.run_config.train.eval_adapt_episodes if episodes is None else episodes
        protocol = "online" if online else f"after {episodes} adaptation episode(s)"
        result = run_policy(s, key, episodes, online)
    elif s.controller == "gp-mpc":
        protocol = "MPC at every step"
        result, stats = run_gp_mpc(s, key)
    elif s.controller == "grbal":
        assert s.grbal is not None
        trainer, saved = s.grbal
        episodes = s.run_config.grbal.eval_adapt_episodes
        protocol = "online" if online else f"after {episodes} adaptation episode(s)"
        raw = trainer.rollouts(saved["model"], saved["norm"], s.tasks, key)
        result = raw["online" if online else "adapt"]
    else:
        assert s.eps is not None
        protocol = f"training-style episode: prior z, MPC on an event with probability {s.eps:g}"
        result, stats = run_policy_mpc(s, key, s.eps)
    wall = time.perf_counter() - t0
    summary = eval_lib.summarize(result, s.tasks, s.env_config.robot_radius)
    record: dict[str, Any] = {
        "label": s.label,
        "controller": s.controller,
        "run": str(s.run) if s.run else None,
        "env": s.env_name,
        "split": s.split,
        "task_seed": None if s.scenarios else s.task_seed,
        "data": s.data,
        "scenarios": s.scenarios,
        "perturbation": s.perturbation,
        "protocol": protocol,
        "eval_seed": eval_seed,
        "seeds": s.seed_ids or [0],
        "tasks": s.task_ids,
        "metrics": {k: v for k, v in summary.items() if not k.endswith("_per_seed")},
        "per_seed": {
            k[: -len("_per_seed")]: v for k, v in summary.items() if k.endswith("_per_seed")
        },
        "per_task": per_task_metrics(result, s.tasks, s.env_config),
        "wall_s": wall,
    }
    if s.controller not in ("policy", "grbal"):
        assert stats is not None
        record["mpc"] = s.mpc
        if s.controller == "policy+mpc":
            record["eps"] = s.eps
        record["mpc_share"] = float(np.mean(result["used_mpc"]))
        record["mpc_status"] = dict(stats["status"])
        record["mpc_reasons"] = dict(stats["reasons"])
    if s.controller in ("policy", "grbal"):
        assert episodes is not None
        record["episodes"] = 1 if online else episodes + 1
        if s.shield is not None:
            record["shield"] = asdict(s.shield)
            record["shield_rate"] = float(np.mean(result["shielded"]))
    record["failures"] = failures([record["per_task"]])
    return record, result, stats


def pooled_record(s: Setup, task_seeds: list[int], records: list[dict]) -> dict:
    """The results.json of several task seeds: the `records` of `run_setup` on the split of each
    task-set seed (`s`: the last one's setup), pooled (`scoring.pooled`: mean and standard error
    over all their tasks, the mean of each set) with their failures."""
    return {
        "label": s.label,
        "split": s.split,
        "perturbation": s.perturbation,
        "task_seeds": task_seeds,
        "num_tasks": sum(len(r["tasks"]) for r in records),
        "pooled": pooled(records),
        "failures": failures([r["per_task"] for r in records]),
        "records": records,
    }
