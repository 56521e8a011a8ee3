"""What `experiments.evaluate` does once its command line is read: the evaluated tasks of a split
(task seed, the paper's scenarios, --tasks, --figures, a crowd perturbation), the MPC settings,
the output folder, the controller run on the tasks and the record it writes (results.json), its
tables and trajectory figures. The command keeps the parsing, the printing and the exit codes;
an error here is a `UsageError` (a bad command line or input file, one line, exit status 2).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.envs import tasks_for
from mpcpearl_jax.envs.perturb import parse_perturbation, perturb_tasks
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.evaluation.metrics import METRIC_NAMES
from mpcpearl_jax.evaluation.runners import (
    Setup,
    run_gp_mpc,
    run_policy,
    run_policy_mpc,
)
from mpcpearl_jax.evaluation.scoring import failures, per_task_metrics, pooled
from mpcpearl_jax.runfolder import RUN_RECORDS
from mpcpearl_jax.validate import unwritable_folder

FIGURES = 4  # default number of tasks with a figure (and a GIF with --animate)


class UsageError(ValueError):
    """A bad command line or input file; reported as one line, exit status 2."""


def _parse_spans(text: str, what: str) -> list[tuple[int, int]]:
    """'0,3,5' | '0-3' (inclusive) | a mix -> its (lo, hi) spans, sorted and merged, never
    expanded (a span may be billions long); UsageError for an empty or reversed range (5-1) and
    for nothing at all."""
    spans: list[tuple[int, int]] = []
    for part in text.split(","):
        a, dash, b = part.partition("-")
        try:
            lo, hi = int(a), (int(b) if dash else int(a))
        except ValueError:
            raise UsageError(f"{what} {text!r}: expected numbers like 0,3,5 or 0-3") from None
        if hi < lo:
            raise UsageError(
                f"{what} {text!r}: the range {part.strip()} is reversed (give A-B, A <= B)"
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


def parse_ranges(
    text: str, what: str, cap: int | None = None, unit: str = "values", hint: str = ""
) -> set[int]:
    """The integers of '0,3,5' | '0-3' | a mix (`_parse_spans`); with `cap`, UsageError when
    there are more than `cap` of them (`unit`, then `hint`), checked before anything is
    expanded."""
    spans = _parse_spans(text, what)
    n = _count(spans)
    if cap is not None and n > cap:
        raise UsageError(f"{what} {text}: {n} {unit}; at most {cap}{hint}")
    return {i for lo, hi in spans for i in range(lo, hi + 1)}


def check_eval_seed(seed: int) -> None:
    """UsageError unless `seed` makes a PRNG key (an integer that fits 64 bits)."""
    try:
        jax.random.PRNGKey(seed)
    except (OverflowError, ValueError, TypeError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise UsageError(f"--eval-seed {seed}: not a PRNG seed ({first})") from None


def probe_out(out: Path, overwrite: bool = False) -> None:
    """Create the output folder and prove it writable before any work (a probe file written and
    removed); UsageError naming it otherwise. A run's folder (it holds a run's records) is never
    an output folder, and an earlier evaluation's results.json is replaced only with
    `overwrite`."""
    records = [name for name in RUN_RECORDS[:4] if (out / name).exists()]
    if records:
        raise UsageError(
            f"--out {out}: a run's folder (it holds {', '.join(records)}); an evaluation never "
            f"writes over a run's records: choose another --out, e.g. {out / 'eval' / 'NAME'}"
        )
    if (out / "results.json").exists() and not overwrite:
        raise UsageError(
            f"--out {out}: holds an earlier evaluation's results.json; pass --overwrite to "
            "replace it, or choose another --out"
        )
    why = unwritable_folder(out)
    if why is not None:
        raise UsageError(f"--out {out}: not writable ({why}); choose another --out")


def parse_indices(text: str, n: int, what: str) -> list[int]:
    """'all' | 'none' | '0,3,5' | '0-3' (inclusive) | a mix -> sorted unique indices < n."""
    text = text.strip().lower()
    if text == "all":
        return list(range(n))
    if text in ("none", ""):
        return []
    spans = _parse_spans(text, what)
    beyond = [(max(lo, n), hi) for lo, hi in spans if hi >= n]  # checked before expanding
    if beyond:
        count = _count(beyond)
        first = [i for lo, hi in beyond for i in range(lo, min(hi, lo + 5) + 1)][:5]
        shown = first if count <= 5 else f"{first[:3]} and {count - 3} more"
        raise UsageError(
            f"{what}: task(s) {shown} out of range; the split has {n} tasks (0-{n - 1})"
        )
    return sorted(i for lo, hi in spans for i in range(lo, hi + 1))


def mpc_overrides(items: list[str], base: dict) -> dict:
    """The MPCConfig fields `base` with the --set FIELD=VALUE `items` on top (read by each
    field's type, `mpcpearl_jax.config.parse_override`), checked; UsageError in one line."""
    from mpcpearl_jax.config import mpc_config, parse_override
    from mpcpearl_jax.mpc import MPCConfig

    out = dict(base)
    try:
        for item in items:
            _, field, value = parse_override(item, {"": MPCConfig})
            out[field] = value
    except ConfigError as e:
        raise UsageError(str(e)) from e
    try:
        mpc_config(out)  # the one check of MPCConfig fields and values
    except ValueError as e:
        raise UsageError(f"--set: {e}") from e
    return out


def task_setup(
    cfg: Any,
    env: Any,
    env_name: str,
    data: str | None,
    split: str,
    *,
    task_seed: int | None = None,
    task_seeds: str | None = None,
    scenarios: Path | None = None,
    tasks: str = "all",
    figures: str | None = None,
    perturb: str = "none",
):
    """The evaluated tasks of a split for a run config `cfg` (None: `env_name`'s defaults), as
    the options name them (--task-seed, --task-seeds, --scenarios, --tasks, --figures,
    --perturb): (task seed, scenario source, tasks, task ids, figure ids, perturbation)."""
    seed = task_seed if task_seed is not None else (cfg.task_seed if cfg else 0)
    source = (cfg or ExperimentConfig(env=env_name)).replace(data=data)
    scenarios = scenario_source(
        cfg, env_name, source.task_options, split, scenarios, task_seed, task_seeds
    )
    if scenarios is not None:  # the paper's scenarios, in place of the run's task source
        source = source.replace(data=None, task_options=scenarios)
    try:
        all_tasks = tasks_for(source, split, config=env.config, seed=seed)
    except (ValueError, TypeError, OSError) as e:
        if isinstance(e, OSError) and scenarios is None:
            raise
        raise UsageError(f"{env_name} --split {split}: {e}") from e
    n = all_tasks.num_tasks
    task_ids = parse_indices(tasks, n, "--tasks")
    if not task_ids:
        raise UsageError("--tasks: no task selected")
    if figures is None:
        figure_ids = task_ids[:FIGURES]
    else:
        figure_ids = parse_indices(figures, n, "--figures")
        missing = sorted(set(figure_ids) - set(task_ids))
        if missing:
            raise UsageError(f"--figures: task(s) {missing} are not evaluated (see --tasks)")
    chosen = jax.tree_util.tree_map(lambda x: x[np.asarray(task_ids)], all_tasks)
    try:
        perturbation = parse_perturbation(perturb)
    except ValueError as e:
        raise UsageError(str(e)) from e
    return (
        seed,
        scenarios,
        perturb_tasks(chosen, perturbation),
        task_ids,
        figure_ids,
        perturbation,
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
    task_seed: int | None = None,
    task_seeds: str | None = None,
) -> dict | None:
    """The task options of the paper's scenarios when they are the task source (--scenarios, or
    the run trained on them), else None. A run that trained on every training scenario is not
    scored on the val split (its tasks 150-179 were training tasks)."""
    from mpcpearl_jax.envs.restaurant.scenarios import check_val_split, scenario_options

    if scenarios is None and not task_options.get("scenarios"):
        return None
    if env_name != "restaurant":
        raise UsageError(f"--scenarios: the paper's scenarios are restaurant tasks, not {env_name}")
    if task_seed is not None or task_seeds is not None:
        raise UsageError("--task-seed(s): the paper's scenarios are one fixed set of tasks")
    trained = dict(cfg.task_options) if cfg else {}
    try:
        if scenarios is not None:
            out = scenario_options(scenarios)
        else:  # the run's own scenarios: the same files it recorded
            out = {k: v for k, v in task_options.items() if k in ("scenarios", "scenario_sha256")}
        check_val_split(trained, split)
    except (ValueError, OSError) as e:
        raise UsageError(f"--scenarios: {e}") from e
    return out


# ---------------------------------------------------------------------------------- output
def tables(record: dict) -> str:
    """Markdown: metrics (mean, per seed), then per task (mean over the evaluated seeds)."""
    seeds = record["seeds"]
    per_seed = record["per_seed"]
    head = ["metric", "mean"] + ([f"seed {s}" for s in seeds] if len(seeds) > 1 else [])
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for k in (*METRIC_NAMES, "return"):
        cells = [f"{record['metrics'][k]:.2f}"]
        if len(seeds) > 1:
            cells += [f"{v:.2f}" for v in per_seed[k]]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    pt = {k: np.asarray(v) for k, v in record["per_task"].items()}
    note = f" (mean over {len(seeds)} seeds)" if len(seeds) > 1 else ""
    lines += ["", f"Per task{note}:", ""]
    cols = ("SR", "CFR", "TT", "SPL", "MGD", "return")
    lines += ["| task | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for j, t in enumerate(record["tasks"]):
        vals = " | ".join(f"{pt[c][:, j].mean():.2f}" for c in cols)
        lines.append(f"| {t} | {vals} |")
    return "\n".join(lines)


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


def evaluate(
    s: Setup, eval_seed: int, episodes: int | None = None, online: bool = False
) -> tuple[dict, dict]:
    """Run the controller on the tasks with the PRNG seed `eval_seed` (`episodes` adaptation
    episodes, None: the run's; or `online`); -> (record for results.json, raw arrays [S, N,
    ...])."""
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
        trainer, saved = s.grbal
        episodes = s.run_config.grbal.eval_adapt_episodes
        protocol = "online" if online else f"after {episodes} adaptation episode(s)"
        raw = trainer.rollouts(saved["model"], saved["norm"], s.tasks, key)
        result = raw["online" if online else "adapt"]
    else:
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
        record["mpc"] = s.mpc
        if s.controller == "policy+mpc":
            record["eps"] = s.eps
        record["mpc_share"] = float(np.mean(result["used_mpc"]))
        record["mpc_status"] = dict(stats["status"])
        record["mpc_reasons"] = dict(stats["reasons"])
    if s.controller in ("policy", "grbal"):
        record["episodes"] = 1 if online else episodes + 1
        if s.shield is not None:
            record["shield"] = asdict(s.shield)
            record["shield_rate"] = float(np.mean(result["shielded"]))
    record["failures"] = failures([record["per_task"]])
    return record, result


def pooled_record(s: Setup, task_seeds: list[int], records: list[dict]) -> dict:
    """The results.json of --task-seeds: the `records` of `evaluate` on the split of each
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
