"""A seed screen: training recipes (arms) over the same seeds, trained one run at a time, and a
report of how they compare, from the run folders alone.

    python -m lab.screen SCREEN.json [--arms A ...] [--seeds S ...] [--dry-run]
                                             [--report-only]

A screen file names its arms and seeds once; every arm is trained with every seed:

    {"name": "learner",
     "results": "results/restaurant/screen",
     "seeds": [0, 1, 2, 3, 4, 5, 6, 7, 8, 9],
     "trainer": "restaurant",
     "common_argv": ["--no-progress"],
     "evaluate": [["--split", "val", "--task-seeds", "1-8", "--figures", "none",
                   "--out", "{results}/eval/policy-val-seeds1-8"]],
     "baseline": "default",
     "arms": {"default": {"argv": [], "runs": {"0": "results/restaurant/main-default", ...}},
              "explore": {"argv": ["--set", "train.explore_start_share=0.5"]}}}

An arm with `runs` reuses finished run folders, one per seed (nothing is trained for it; their
configs must be the ones its argv builds with each seed). An arm with `"iterations_of": ARM`
(ARM an arm of reused runs) trains each seed for as many iterations as ARM's run of that seed
finished (`--iterations N` after its argv and `common_argv`, which then give no budget of their
own): a comparison at equal iterations with runs that had a time budget. An arm marked
`"retired"` (a line naming the options since removed that its argv sets,
`config.REMOVED_OPTIONS`) is reported from its run folders, `<results>/<arm>-s<S>`, and never
trained or rebuilt. An arm with `argv` only is trained:
seed S becomes the campaign entry `<name>-<arm>-s<S>` with argv = the arm's argv, then
`common_argv`, then `--seed S`, results folder `<results>/<arm>-s<S>` and the screen's `evaluate`
list, and the entries are trained seed by seed, each arm in turn (an interrupted screen leaves its
arms on equal seeds), as `lab.campaign` trains its queue (one at a time in
`runs/campaign/<entry>`, resumed after Ctrl-C by the same command, copied without checkpoints, then
evaluated). `--arms` and `--seeds` train only the arms and seeds named; `--dry-run` prints the
entries and the processes left and runs nothing; `--report-only` trains nothing. The first
`evaluate` entry must be a `--split val` evaluation: its record is the validation the report reads.

The report (`<results>/<name>.json` and the figure `<results>/<name>-liftoff.png`) covers every
arm and only its finished seeds (a run folder with results.json, metrics.jsonl, config.json and
the validation record), naming the others; nothing is filled in. Per seed: lift-off, the first
training iteration whose `train_success` is above 0 (a training episode from the task's start
reached the goal), as its iteration, gradient steps (iteration x `train.updates_per_iteration`)
and wall-clock minutes since the run started (`wall_s` of that iteration's row); a run that never
lifts off is censored at its budget. Per arm: validation SR (mean +- standard error over seeds,
worst seed), the seeds with validation and test SR >= PASS, the fraction of seeds lifted off by
each gradient step and minute, and the interquartile mean (IQM) of the seeds' validation SR and
SPL with a 95 % stratified-bootstrap interval and the probability that a seed of the arm beats a
seed of the baseline arm, with its interval (rliable; REPS bootstrap samples drawn from a fixed
seed, so the report is the same every time it is made from the same records).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lab import campaign
from lab.tables import statistics
from lab.tables.statistics import Records, cumulative_wall_s

KEYS = ("name", "results", "seeds", "trainer", "common_argv", "evaluate", "baseline", "arms")
ARM_KEYS = ("argv", "runs", "retired", "iterations_of")
TRAINERS = ("restaurant",)  # trainers whose records the report reads (metrics.jsonl, results.json)
SET_BY_SCREEN = ("--seed", "--out", "--resume", "--overwrite")
BUDGET_FLAGS = ("--iterations", "--minutes", "--eval-minutes")  # not beside 'iterations_of'
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*\Z")  # a screen or arm name: one folder name
METRICS = ("SR", "CFR", "TT", "SPL")  # the validation metrics of the report
BOOTSTRAP_METRICS = ("SR", "SPL")  # IQM and probability of improvement
PASS = 0.3  # a seed passes with validation SR and test SR both at least this
REPS = 2000  # bootstrap samples per interval
BOOTSTRAP_SEED = 0


@dataclass(frozen=True)
class Arm:
    name: str
    argv: tuple[str, ...]
    runs: dict[int, Path] | None = None  # reused run folders by seed; None: trained
    retired: str | None = None  # the removed options its argv sets: reported, never trained
    iterations_of: str | None = None  # an arm of reused runs: seed S trains as many iterations


@dataclass(frozen=True)
class Screen:
    path: Path
    name: str
    results: Path
    seeds: tuple[int, ...]
    trainer: str
    common_argv: tuple[str, ...]
    evaluate: tuple[tuple[str, ...], ...]  # as the file has them ({results} unresolved)
    baseline: str
    arms: dict[str, Arm]

    def folder(self, arm: str, seed: int) -> Path:
        """The run folder of one arm and seed: the reused one, or `<results>/<arm>-s<seed>`."""
        runs = self.arms[arm].runs
        return runs[seed] if runs is not None else self.results / f"{arm}-s{seed}"

    def argv(self, arm: str, seed: int) -> list[str]:
        matched = self.arms[arm].iterations_of
        budget = [] if matched is None else ["--iterations", str(self.iterations(matched, seed))]
        return [*self.arms[arm].argv, *self.common_argv, *budget, "--seed", str(seed)]

    def iterations(self, arm: str, seed: int) -> int:
        """The iterations the reused run of `arm` and `seed` trained (its metrics.jsonl's last
        row); ValueError naming the file when it has none."""
        path = self.folder(arm, seed) / "metrics.jsonl"
        try:
            return int(_read(path)[-1]["iteration"])
        except (OSError, IndexError, KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{path}: no finished iteration to match ({e})") from None

    def entry(self, arm: str, seed: int) -> dict[str, Any]:
        """The campaign entry that trains one arm and seed."""
        return {
            "name": f"{self.name}-{arm}-s{seed}",
            "trainer": self.trainer,
            "argv": self.argv(arm, seed),
            "results": str(self.folder(arm, seed)),
            "evaluate": [list(e) for e in self.evaluate],
        }

    @property
    def validation(self) -> str:
        """The validation record, relative to a run folder (the first evaluation's --out)."""
        first = self.evaluate[0]
        return first[first.index("--out") + 1].removeprefix("{results}/") + "/results.json"

    @property
    def report_path(self) -> Path:
        return self.results / f"{self.name}.json"

    @property
    def figure_path(self) -> Path:
        return self.results / f"{self.name}-liftoff.png"


def _strings(x: object) -> bool:
    return isinstance(x, list) and all(isinstance(a, str) for a in x)


def _check_argv(argv: object, where: str) -> tuple[str, ...]:
    if not isinstance(argv, list) or not _strings(argv):
        raise ValueError(f"{where} must be a list of strings")
    held = [a for a in argv if a.split("=")[0] in SET_BY_SCREEN]
    if held:
        raise ValueError(f"{where} must not hold {held[0]} (the screen sets it)")
    return tuple(argv)


def load_screen(path: Path) -> Screen:
    """The screen a file describes; ValueError naming the file and the field on a bad one."""
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable JSON screen ({e})") from e
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a JSON object with {list(KEYS)}")
    unknown = sorted(set(raw) - set(KEYS))
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {unknown}; a screen file holds {list(KEYS)}")
    needed = [k for k in KEYS if k not in raw and k not in ("trainer", "common_argv")]
    if needed:
        raise ValueError(f"{path}: missing key(s) {needed}")
    name = raw["name"]
    if not isinstance(name, str) or not NAME.match(name):
        raise ValueError(
            f"{path}: 'name' must be a folder name (letters, digits, '_', '.', '-'), got {name!r}"
        )
    if not isinstance(raw["results"], str) or not raw["results"].strip():
        raise ValueError(f"{path}: 'results' must be a folder path (a string)")
    seeds = raw["seeds"]
    if (
        not isinstance(seeds, list)
        or not seeds
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds)
        or len(set(seeds)) != len(seeds)
    ):
        raise ValueError(f"{path}: 'seeds' must be a non-empty list of unique integers >= 0")
    trainer = raw.get("trainer", "restaurant")
    if trainer not in TRAINERS:
        raise ValueError(f"{path}: 'trainer' must be one of {list(TRAINERS)}, got {trainer!r}")
    common = _check_argv(raw.get("common_argv", []), f"{path}: 'common_argv'")
    evals = raw["evaluate"]
    if not isinstance(evals, list) or not evals or not all(_strings(e) for e in evals):
        raise ValueError(f"{path}: 'evaluate' must be a non-empty list of argument lists")
    for i, args in enumerate(evals):
        out = args[args.index("--out") + 1] if "--out" in args[:-1] else ""
        if not out.startswith("{results}/") or out.rstrip("/") == "{results}":
            raise ValueError(
                f"{path}: 'evaluate'[{i}] must give --out {{results}}/FOLDER (inside each run)"
            )
    if "--split" not in evals[0][:-1] or evals[0][evals[0].index("--split") + 1] != "val":
        raise ValueError(
            f"{path}: 'evaluate'[0] must be a --split val evaluation (the report reads it)"
        )
    arms_raw = raw["arms"]
    if not isinstance(arms_raw, dict) or not arms_raw:
        raise ValueError(f"{path}: 'arms' must be a non-empty object of arm name -> arm")
    arms: dict[str, Arm] = {}
    for arm, spec in arms_raw.items():
        where = f"{path}: arms.{arm}"
        if not NAME.match(arm):
            raise ValueError(
                f"{path}: 'arms': {arm!r} is not a folder name (letters, digits, '_', '.', '-')"
            )
        if not isinstance(spec, dict):
            raise ValueError(f"{where}: expected an object with {list(ARM_KEYS)}")
        unknown = sorted(set(spec) - set(ARM_KEYS))
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {unknown}; an arm holds {list(ARM_KEYS)}")
        argv = _check_argv(spec.get("argv", []), f"{where}: 'argv'")
        runs = spec.get("runs")
        if runs is not None:
            runs = _reused_runs(runs, seeds, f"{where}: 'runs'")
        retired = spec.get("retired")
        if retired is not None and (not isinstance(retired, str) or not retired.strip()):
            raise ValueError(f"{where}: 'retired' must name the removed options (a string)")
        matched = spec.get("iterations_of")
        if matched is not None:
            if runs is not None or retired is not None:
                raise ValueError(f"{where}: 'iterations_of' is for a trained arm, not with 'runs'")
            budget = [a for a in (*argv, *common) if a.split("=")[0] in BUDGET_FLAGS]
            if budget:
                raise ValueError(
                    f"{where}: with 'iterations_of' its argv and common_argv must not hold "
                    f"{budget[0]} (the matched iterations are its budget)"
                )
        arms[arm] = Arm(arm, argv, runs, retired, matched)
    for arm in arms.values():
        if arm.iterations_of is not None and (
            arm.iterations_of not in arms or arms[arm.iterations_of].runs is None
        ):
            raise ValueError(
                f"{path}: arms.{arm.name}: 'iterations_of' must name an arm with 'runs' "
                f"({[a for a in arms if arms[a].runs is not None]}), got {arm.iterations_of!r}"
            )
    baseline = raw["baseline"]
    if baseline not in arms:
        raise ValueError(f"{path}: 'baseline' must name an arm ({list(arms)}), got {baseline!r}")
    return Screen(
        Path(path),
        name,
        Path(raw["results"]),
        tuple(seeds),
        trainer,
        common,
        tuple(tuple(e) for e in evals),
        baseline,
        arms,
    )


def _reused_runs(runs: object, seeds: list[int], where: str) -> dict[int, Path]:
    if not isinstance(runs, dict):
        raise ValueError(f"{where} must be an object of seed -> run folder")
    out: dict[int, Path] = {}
    for key, folder in runs.items():
        if not key.isdigit() or int(key) not in seeds or str(int(key)) != key:
            raise ValueError(f"{where}: {key!r} is not one of the screen's seeds {seeds}")
        if not isinstance(folder, str) or not folder.strip():
            raise ValueError(f"{where}: seed {key}: the run folder must be a path (a string)")
        out[int(key)] = Path(folder)
    absent = [s for s in seeds if s not in out]
    if absent:
        raise ValueError(f"{where}: no run folder for seed(s) {absent}")
    return out


def campaign_runs(screen: Screen) -> dict[str, list[campaign.CampaignRun]]:
    """Arm -> its campaign entries in seed order (none for an arm that reuses runs or is
    retired), each checked as a campaign file's entry is; ValueError naming the file and the
    arm."""
    out: dict[str, list[campaign.CampaignRun]] = {}
    for arm in screen.arms.values():
        out[arm.name] = []
        if arm.runs is not None or arm.retired is not None:
            continue
        for seed in screen.seeds:
            where = f"{screen.path}: arms.{arm.name} (seed {seed})"
            out[arm.name].append(campaign.parse_entry(screen.entry(arm.name, seed), where))
    return out


def check_reused(screen: Screen, arms: list[str]) -> None:
    """ValueError when a reused run folder's config.json is not the config its arm's argv
    builds with that seed (the arm would not be the recipe it says)."""
    for name in arms:
        arm = screen.arms[name]
        for seed, folder in (arm.runs or {}).items():
            run = campaign.CampaignRun(
                f"{screen.name}-{name}-s{seed}",
                tuple(screen.argv(name, seed)),
                folder,
                trainer=screen.trainer,
            )
            campaign.check_unchanged(run, folder)


# ---------------------------------------------------------------- the report


def _read(path: Path) -> Any:
    if path.suffix == ".jsonl":
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return json.loads(path.read_text())


def missing_records(folder: Path, validation: str) -> list[str]:
    """The records of a finished run that `folder` lacks."""
    need = ("results.json", "metrics.jsonl", "config.json", validation)
    return [rel for rel in need if not (folder / rel).is_file()]


def liftoff(rows: list[dict], updates_per_iteration: int) -> tuple[dict | None, dict]:
    """(lift-off, budget) of one run's metrics.jsonl rows: the first iteration whose
    `train_success` is above 0 as {iteration, grad_steps, minutes} (None: it never lifted off),
    and the last iteration the same way."""
    rows = [r for r in rows if "iteration" in r]
    walls = cumulative_wall_s(rows)

    def point(i: int) -> dict:
        it = int(rows[i]["iteration"])
        return {
            "iteration": it,
            "grad_steps": it * updates_per_iteration,
            "minutes": walls[i] / 60,
        }

    first = next((i for i, r in enumerate(rows) if (r.get("train_success") or 0) > 0), None)
    return (None if first is None else point(first)), point(len(rows) - 1)


def seed_report(folder: Path, validation: str) -> dict:
    """One finished run folder's lift-off, budget, validation metrics and test SR; ValueError
    naming the folder when a record does not hold what a finished run's does."""
    try:
        cfg = _read(folder / "config.json")
        rows = _read(folder / "metrics.jsonl")
        if not any("iteration" in r for r in rows):
            raise ValueError("metrics.jsonl logs no iteration")
        lifted, budget = liftoff(rows, cfg["train"]["updates_per_iteration"])
        pooled = _read(folder / validation)["pooled"]
        return {
            "liftoff": lifted,
            "budget": budget,
            "val": {m: pooled[m]["mean"] for m in METRICS},
            "test_SR": _read(folder / "results.json")["test_adapt"]["SR"],
        }
    except (OSError, ValueError, KeyError, TypeError) as e:  # JSONDecodeError is a ValueError
        raise ValueError(f"{folder}: not a finished run's records ({type(e).__name__}: {e})") from e


def seed_stats(values: list[float], metric: str) -> dict:
    """Mean, standard error over seeds (ddof 1; None below two seeds) and the worst seed
    (`tables.statistics.seed_stats`)."""
    if len(values) < 2:
        return {"mean": values[0], "se": None, "worst": values[0]}
    mean, se, worst = statistics.seed_stats(values, metric)
    return {"mean": mean, "se": se, "worst": worst}


def liftoff_curve(times: list[float | None]) -> list[list[float]]:
    """The fraction of runs lifted off by each time a run lifted off: [[time, fraction], ...];
    a run that never lifted off (None) counts as not lifted off at every time."""
    done = sorted(t for t in times if t is not None)
    n = len(times)
    curve: list[list[float]] = []
    for i, t in enumerate(done):
        if curve and curve[-1][0] == t:
            curve[-1][1] = (i + 1) / n
        else:
            curve.append([t, (i + 1) / n])
    return curve


def curve_median(curve: list[list[float]]) -> float | None:
    """The first time by which half the runs had lifted off (None: fewer than half ever did)."""
    return next((t for t, frac in curve if frac >= 0.5), None)


def _bootstrap(
    scores: dict[str, Any], fn, reps: int | None, seed: int | None
) -> tuple[float, list[float]]:
    """rliable's stratified-bootstrap point estimate and 95 % percentile interval of `fn` for
    one entry of `scores` (arrays shaped [runs, 1], or a tuple of them), `reps` samples drawn
    from `seed` (REPS, BOOTSTRAP_SEED where None). rliable resamples with NumPy's global
    generator: it is seeded here and its state restored after."""
    import numpy as np
    from rliable import library as rly

    reps = REPS if reps is None else reps
    seed = BOOTSTRAP_SEED if seed is None else seed
    state = np.random.get_state()  # noqa: NPY002 (rliable draws from the global generator)
    try:
        np.random.seed(seed)  # noqa: NPY002
        point, interval = rly.get_interval_estimates(scores, fn, reps=reps)
    finally:
        np.random.set_state(state)  # noqa: NPY002
    (key,) = scores
    lo, hi = interval[key][:, 0]
    return float(point[key][0]), [float(lo), float(hi)]


def iqm(scores: list[float], reps: int | None = None, seed: int | None = None) -> dict:
    """The interquartile mean of one arm's per-seed scores and its bootstrap interval (REPS
    samples from BOOTSTRAP_SEED unless given)."""
    import numpy as np
    from rliable import metrics

    x = np.asarray(scores, dtype=float)[:, None]
    value, ci = _bootstrap({"arm": x}, lambda s: np.array([metrics.aggregate_iqm(s)]), reps, seed)
    return {"scores": list(scores), "value": value, "ci": ci}


def improvement(
    scores: list[float], baseline: list[float], reps: int | None = None, seed: int | None = None
) -> dict:
    """P(a seed of the arm scores higher than a seed of the baseline; ties count half) and its
    bootstrap interval (the two arms resampled independently)."""
    import numpy as np
    from rliable import metrics

    x = np.asarray(scores, dtype=float)[:, None]
    y = np.asarray(baseline, dtype=float)[:, None]

    def fn(a, b):
        return np.array([metrics.probability_of_improvement(a, b)])

    value, ci = _bootstrap({"arm,baseline": (x, y)}, fn, reps, seed)
    return {"scores": list(scores), "baseline_scores": list(baseline), "value": value, "ci": ci}


def _memo(previous: dict | None) -> dict[tuple, dict]:
    """The bootstrap results of an earlier report by their inputs: each depends on its scores,
    REPS and BOOTSTRAP_SEED only, so a report made again from unchanged records reuses them."""
    memo: dict[tuple, dict] = {}
    if not isinstance(previous, dict):
        return memo
    if previous.get("bootstrap") != {"reps": REPS, "seed": BOOTSTRAP_SEED}:
        return memo
    for arm in (previous.get("arms") or {}).values():
        for entry in (arm.get("iqm") or {}).values():
            if entry:
                memo[("iqm", tuple(entry["scores"]))] = entry
        for entry in (arm.get("improvement") or {}).values():
            if entry:
                memo[("poi", tuple(entry["scores"]), tuple(entry["baseline_scores"]))] = entry
    return memo


def screen_report(screen: Screen, root: Path = Path("."), previous: dict | None = None) -> dict:
    """The screen's report from its run folders under `root` (finished seeds only; the others
    are listed under `missing` with the records they lack). `previous`: an earlier report whose
    bootstrap results are reused where their inputs are the same (the result is the same)."""
    memo = _memo(previous)
    arms: dict[str, dict] = {}
    for name in screen.arms:
        runs, missing = [], {}
        for seed in screen.seeds:
            folder = screen.folder(name, seed)
            lacks = missing_records(root / folder, screen.validation)
            if lacks:
                missing[str(seed)] = {"run": str(folder), "lacks": lacks}
            else:
                record = seed_report(root / folder, screen.validation)
                runs.append({"seed": seed, "run": str(folder), **record})
        arms[name] = {
            "seeds": list(screen.seeds),
            "finished": [r["seed"] for r in runs],
            "missing": missing,
            "runs": runs,
        }
        arms[name].update(_arm_summary(runs))
    base = [r["val"] for r in arms[screen.baseline]["runs"]]
    for name, arm in arms.items():
        vals = [r["val"] for r in arm["runs"]]
        arm["iqm"] = {}
        arm["improvement"] = {}
        for m in BOOTSTRAP_METRICS:
            x = [v[m] for v in vals]
            y = [v[m] for v in base]
            arm["iqm"][m] = None
            if len(x) >= 2:
                arm["iqm"][m] = memo.get(("iqm", tuple(x))) or iqm(x)
            arm["improvement"][m] = None
            if name != screen.baseline and len(x) >= 2 and len(y) >= 2:
                key = ("poi", tuple(x), tuple(y))
                arm["improvement"][m] = memo.get(key) or improvement(x, y)
    return {
        "screen": screen.name,
        "file": str(screen.path),
        "baseline": screen.baseline,
        "pass": PASS,
        "bootstrap": {"reps": REPS, "seed": BOOTSTRAP_SEED},
        "arms": arms,
    }


def _arm_summary(runs: list[dict]) -> dict:
    if not runs:
        return {"val": None, "test_SR": None, "passed": 0, "lifted": 0, "liftoff": None}
    curves: dict[str, Any] = {}
    for unit in ("grad_steps", "minutes"):
        times = [None if r["liftoff"] is None else r["liftoff"][unit] for r in runs]
        curve = liftoff_curve(times)
        curves[unit] = {
            "curve": curve,
            "median": curve_median(curve),
            "budget": max(r["budget"][unit] for r in runs),
        }
    return {
        "val": {m: seed_stats([r["val"][m] for r in runs], m) for m in METRICS},
        "test_SR": seed_stats([r["test_SR"] for r in runs], "SR"),
        "passed": sum(r["val"]["SR"] >= PASS and r["test_SR"] >= PASS for r in runs),
        "lifted": sum(r["liftoff"] is not None for r in runs),
        "liftoff": curves,
    }


def read_report(path: Path) -> dict | None:
    """An earlier report, or None where there is none (or it does not parse)."""
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def write_report(report: dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(report, indent=1) + "\n")
    os.replace(tmp, path)


def write_figure(report: dict, path: Path) -> None:
    """The fraction of each arm's finished seeds lifted off by each gradient step: one step
    curve per arm, each to its budget."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for name, arm in report["arms"].items():
        if not arm["runs"]:
            continue
        lo = arm["liftoff"]["grad_steps"]
        xs = [0.0] + [t for t, _ in lo["curve"]] + [lo["budget"]]
        ys = [0.0] + [f for _, f in lo["curve"]]
        ys.append(ys[-1])
        n = len(arm["runs"])
        label = f"{name} ({arm['lifted']}/{n} lifted off)"
        ax.step(xs, ys, where="post", label=label)
    ax.set_xlabel("gradient steps")
    ax.set_ylabel("fraction of seeds lifted off")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"screen {report['screen']}: first training success from the start")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _summary_lines(report: dict) -> list[str]:
    out = []
    for name, arm in report["arms"].items():
        n, total = len(arm["finished"]), len(arm["seeds"])
        line = f"[screen] {name}: {n}/{total} seeds finished"
        # a seed without a training record is not trained yet; the others name what they lack
        bare = [s for s, m in arm["missing"].items() if "metrics.jsonl" in m["lacks"]]
        partial = {s: m for s, m in arm["missing"].items() if s not in bare}
        if partial:
            shown = ", ".join(
                f"s{seed} ({m['run']}: no {', '.join(m['lacks'])})" for seed, m in partial.items()
            )
            line += f"; missing {shown}"
        if bare:
            line += f"; not trained: {' '.join(f's{seed}' for seed in bare)}"
        out.append(line)
    return out


# ---------------------------------------------------------------- the table
# one row per arm, made from the screen's run folders (its report `<results>/<name>.json` only
# saves recomputing a bootstrap whose inputs have not changed). An arm with unfinished seeds
# shows the finished ones and says how many of how many; nothing is filled in.
NONE = "-"


def _f2(x: float) -> str:
    return f"{x:.2f}"


def _mean_se(stats: dict | None) -> str:
    if stats is None:
        return NONE
    se = stats["se"]
    return _f2(stats["mean"]) + ("" if se is None else f" +- {_f2(se)}")


def _interval(entry: dict | None) -> str:
    if entry is None:
        return NONE
    lo, hi = entry["ci"]
    return f"{_f2(entry['value'])} [{_f2(lo)}, {_f2(hi)}]"


def _steps(x: float | None) -> str:
    return NONE if x is None else str(int(round(x)))


def render_screen_report(report: dict) -> str:
    """The Markdown table of a screen's report: validation SR over seeds, IQM and probability of
    improvement with their intervals, lift-off, passes; then the same for validation SPL."""
    base = report["baseline"]
    lines = [
        "| arm | seeds | lifted off | median lift-off (gradient steps) | val SR | worst seed "
        "| IQM val SR [95 % CI] | P(better than baseline) val SR [95 % CI] "
        f"| val SR and test SR >= {PASS} | val CFR | val TT | val SPL |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    spl = [
        "| arm | IQM val SPL [95 % CI] | P(better than baseline) val SPL [95 % CI] |",
        "|---|---|---|",
    ]
    for name, arm in report["arms"].items():
        n, total = len(arm["finished"]), len(arm["seeds"])
        seeds = str(n) if n == total else f"{n}/{total} seeds"
        val = arm["val"] or {}
        poi = {m: _interval(e) for m, e in arm["improvement"].items()}
        if name == base:
            poi = {m: "(baseline)" for m in poi}
        median = arm["liftoff"]["grad_steps"]["median"] if arm["liftoff"] else None
        worst = NONE if not val else _f2(val["SR"]["worst"])
        cells = [
            f"`{name}`",
            seeds,
            f"{arm['lifted']}/{n}",
            _steps(median),
            _mean_se(val.get("SR")),
            worst,
            _interval(arm["iqm"]["SR"]),
            poi["SR"],
            f"{arm['passed']} of {n}",
            _mean_se(val.get("CFR")),
            _mean_se(val.get("TT")),
            _mean_se(val.get("SPL")),
        ]
        lines.append("| " + " | ".join(cells) + " |")
        spl.append(f"| `{name}` | {_interval(arm['iqm']['SPL'])} | {poi['SPL']} |")
    return "\n".join([*lines, "", *spl])


def render_screen(rec: Records, screen_file: str) -> str:
    """The table of the screen file `screen_file` (a path from the repository root, the folder
    above `rec.results`), from its run folders."""
    root = rec.results.parent
    screen = load_screen(root / screen_file)
    report = screen_report(screen, root, read_report(root / screen.report_path))
    return render_screen_report(report)


def render_screen_learner(rec: Records) -> str:
    return render_screen(rec, str(Path("lab") / "screens" / "learner.json"))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m lab.screen",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("screen", type=Path)
    p.add_argument(
        "--arms", nargs="+", default=None, help="train these arms only (the report has them all)"
    )
    p.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        default=None,
        help="train these of the screen's seeds only (the report has them all)",
    )
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--dry-run", action="store_true", help="print what would run, run nothing")
    mode.add_argument("--report-only", action="store_true", help="train nothing; write the report")
    args = p.parse_args(argv)
    try:
        screen = load_screen(args.screen)
        runs = campaign_runs(screen)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    arms = list(screen.arms) if args.arms is None else args.arms
    unknown = [a for a in arms if a not in screen.arms]
    if unknown:
        print(f"error: --arms: no arm named {unknown} in {args.screen}", file=sys.stderr)
        return 2
    seeds = list(screen.seeds) if args.seeds is None else args.seeds
    stray = [s for s in seeds if s not in screen.seeds]
    if stray:
        print(f"error: --seeds: {stray} not among {args.screen}'s seeds", file=sys.stderr)
        return 2
    if not args.report_only:
        try:
            check_reused(screen, arms)
        except ValueError as e:
            print(f"error: {args.screen}: {e}", file=sys.stderr)
            return 2
        for name in arms:
            if screen.arms[name].retired is not None:
                why = screen.arms[name].retired
                print(f"[screen] {name}: retired ({why}); reported, not trained", flush=True)
            elif screen.arms[name].runs is not None:
                print(f"[screen] {name}: reuses {len(screen.seeds)} run folders", flush=True)
        # seed by seed, each arm in turn: an interrupted screen leaves its arms on equal seeds
        todo = []
        for seed in seeds:
            for name in arms:
                if not runs[name]:  # reused or retired: nothing to train
                    continue
                run = runs[name][screen.seeds.index(seed)]
                if args.dry_run:
                    cmd = " ".join([run.module, *run.argv])
                    print(f"[screen] {run.name}: {cmd} -> {run.results}", flush=True)
                todo.append(run)
        lock = campaign.WORK / f".{args.screen.resolve().name}.screen"
        rc = campaign.run_all(todo, lock, args.dry_run, source=str(args.screen))
        if rc or args.dry_run:
            return rc
    try:
        report = screen_report(screen, Path("."), read_report(screen.report_path))
    except ValueError as e:
        print(f"error: {args.screen}: {e}", file=sys.stderr)
        return 2
    write_report(report, screen.report_path)
    write_figure(report, screen.figure_path)
    for line in _summary_lines(report):
        print(line, flush=True)
    print(f"[screen] wrote {screen.report_path} and {screen.figure_path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
