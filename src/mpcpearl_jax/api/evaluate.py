"""`mpcpearl_jax.evaluate`: a trained run (its folder, or loaded policies), or the GP-MPC
baseline, on a task source, with a controller -> the results the evaluation command prints and
writes.

    import mpcpearl_jax

    ev = mpcpearl_jax.evaluate("results/restaurant/main-default", split="val", task_seeds="1-8")
    ev.metrics["SR"], ev.record          # the pooled numbers, what results.json holds
    ev = mpcpearl_jax.evaluate(controller="gp-mpc", env="restaurant", split="val", tasks="0-3",
                               preset="default", out="runs/eval/teacher")   # files too

The task source: `split` with the run's task-set seed (or `task_seed`, or several `task_seeds`
pooled), or the paper's `scenarios` folder, or a trajectory file (`data`); `tasks` picks tasks of
the split ('all', '0,3,5', '0-3' inclusive, '0:4' with 4 excluded, a mix, or a list of ints).
The controller: "policy" (the meta-test protocol; with `shield` through the test-time safety
shield), "gp-mpc" (the risk-aware MPC at every step, with the run's MPC settings, or a `preset`'s,
and `mpc` changes on top), "policy+mpc" (training-style episodes with MPC infusion, `eps`). A
GrBAL run is evaluated with its own controller. `prepare` resolves and checks every argument
without running anything (an `EvaluationError`, one line naming the argument); `Plan.run` runs.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mpcpearl_jax.evaluation.evaluate import EVAL_SEED
from mpcpearl_jax.evaluation.plan import (
    EvaluationError,
    check_eval_seed,
    check_out,
    default_out,
    mpc_settings,
    parse_ranges,
    pooled_record,
    run_setup,
    task_setup,
    write_figures,
)
from mpcpearl_jax.evaluation.runners import Setup
from mpcpearl_jax.mpc.shield import ShieldConfig

__all__ = [
    "CONTROLLERS",
    "Evaluation",
    "EvaluationError",
    "EvaluationOptions",
    "Plan",
    "evaluate",
    "prepare",
]

CONTROLLERS = ("policy", "gp-mpc", "policy+mpc")
MAX_TASK_SEEDS = 100  # task-set seeds in one evaluation (each one is a full evaluation)


@dataclass(frozen=True)
class EvaluationOptions:
    """The keyword arguments of `evaluate` and `prepare`, with their defaults (module doc).
    `env`: the task family without a run (NAME, or MODULE:NAME importing MODULE to register it;
    default restaurant); `episodes`: adaptation episodes before the scored one (default the
    run's) or `online`; `seed_index`: one seed of the run; `shield`: True or a ShieldConfig;
    `eps`: policy+mpc's MPC probability (default the run's); `preset`: the MPC settings of a
    training preset; `mpc`: MPCConfig changes ('FIELD=VALUE' strings or a mapping); `eval_seed`:
    the PRNG seed (GP-MPC: of its GP samples); `figures`: the tasks with a trajectory figure
    (default the first 4 evaluated; 'none'), `animate` a GIF of each too; `out`: the folder
    written into, `overwrite` replacing an earlier results.json there."""

    controller: str = "policy"
    env: str | None = None
    split: str = "test"
    tasks: str | Sequence[int] = "all"
    task_seed: int | None = None
    task_seeds: str | Sequence[int] | None = None
    scenarios: str | Path | None = None
    data: str | Path | None = None
    perturb: str = "none"
    episodes: int | None = None
    online: bool = False
    seed_index: int | None = None
    shield: bool | ShieldConfig = False
    eps: float | None = None
    preset: str | None = None
    mpc: Mapping[str, Any] | Sequence[str] = ()
    eval_seed: int = EVAL_SEED
    figures: str | Sequence[int] | None = None
    animate: bool = False
    out: str | Path | None = None
    overwrite: bool = False

    @classmethod
    def of(cls, options: Mapping[str, Any], caller: str) -> EvaluationOptions:
        """The options of these keyword arguments; TypeError naming `caller` and an unknown
        one, as a call with an unexpected keyword argument gives."""
        names = cls.names()
        for name in options:
            if name not in names:
                raise TypeError(f"{caller}() got an unexpected keyword argument {name!r}")
        why = _wrong_type(options)
        if why is not None:
            raise TypeError(f"{caller}(): {why}")
        return cls(**options)

    def __post_init__(self) -> None:
        """Each option's type checked when built: TypeError naming the option."""
        why = _wrong_type(self.arguments())
        if why is not None:
            raise TypeError(f"EvaluationOptions: {why}")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The options' names, in the order of the signature."""
        return tuple(f.name for f in dataclasses.fields(cls))

    def arguments(self) -> dict[str, Any]:
        """The options as keyword arguments (the values as given, not copied)."""
        return {name: getattr(self, name) for name in self.names()}


def _wrong_type(options: Mapping[str, Any]) -> str | None:
    """The first of `options` (EvaluationOptions' names) whose type is wrong, as "NAME must be
    EXPECTED, not TYPE VALUE"; None when each is of its type (the values are checked later)."""
    import numbers
    import os

    def integer(x: Any) -> bool:
        return isinstance(x, numbers.Integral) and not isinstance(x, bool)

    def text_or_ints(x: Any) -> bool:
        return isinstance(x, str) or (
            hasattr(x, "__len__") and not isinstance(x, Mapping) and all(integer(i) for i in x)
        )

    def strings(x: Any) -> bool:
        return isinstance(x, Mapping) or (
            isinstance(x, (list, tuple)) and all(isinstance(i, str) for i in x)
        )

    ints = "a text like '0-9,12' or a list of ints"
    kinds: dict[str, tuple[Callable[[Any], bool], str]] = {
        "online": (lambda x: isinstance(x, bool), "True or False"),
        "animate": (lambda x: isinstance(x, bool), "True or False"),
        "overwrite": (lambda x: isinstance(x, bool), "True or False"),
        "eval_seed": (integer, "an int"),
        "episodes": (lambda x: x is None or integer(x), "an int (or None)"),
        "task_seed": (lambda x: x is None or integer(x), "an int (or None)"),
        "seed_index": (lambda x: x is None or integer(x), "an int (or None)"),
        "eps": (
            lambda x: x is None or (isinstance(x, numbers.Real) and not isinstance(x, bool)),
            "a number (or None)",
        ),
        "controller": (lambda x: isinstance(x, str), "a string"),
        "split": (lambda x: isinstance(x, str), "a string"),
        "perturb": (lambda x: isinstance(x, str), "a string"),
        "env": (lambda x: x is None or isinstance(x, str), "a string (or None)"),
        "preset": (lambda x: x is None or isinstance(x, str), "a string (or None)"),
        "tasks": (text_or_ints, f"'all', {ints}"),
        "task_seeds": (lambda x: x is None or text_or_ints(x), f"{ints} (or None)"),
        "figures": (lambda x: x is None or text_or_ints(x), f"'none', {ints} (or None)"),
        "mpc": (strings, "a mapping or a list of 'FIELD=VALUE' strings"),
        "shield": (lambda x: isinstance(x, (bool, ShieldConfig)), "True, False or a ShieldConfig"),
        "scenarios": (lambda x: x is None or isinstance(x, (str, os.PathLike)), "a path (or None)"),
        "data": (lambda x: x is None or isinstance(x, (str, os.PathLike)), "a path (or None)"),
        "out": (lambda x: x is None or isinstance(x, (str, os.PathLike)), "a path (or None)"),
    }
    for name, x in options.items():
        ok, expected = kinds.get(name, (lambda _: True, ""))
        if not ok(x):
            return f"{name} must be {expected}, not {type(x).__name__} {x!r}"
    return None


@dataclass
class Evaluation:
    """What an evaluation gives. `record`: what results.json holds (one task set: metrics, per
    seed and per task, failures, the protocol; several task seeds: the pooled means and standard
    errors with each set's record); `result`: the episodes' arrays [S, N, ...] (seeds, tasks;
    None for several task seeds); `stats`: the MPC's statistics (its status and reasons counts,
    solve times; None without the MPC); `setup`: the (last) task set's resolved setup; `out` and
    `written`: the folder and the files written (None and [] when nothing was)."""

    record: dict
    result: dict | None
    stats: dict | None
    setup: Setup
    out: Path | None = None
    written: list[Path] = field(default_factory=list)

    @property
    def metrics(self) -> dict:
        """SR, CFR, TT, SPL, MGD and return: the means (pooled over task sets when several)."""
        if "pooled" in self.record:
            return {k: v["mean"] for k, v in self.record["pooled"].items()}
        return self.record["metrics"]


@dataclass
class Plan:
    """A resolved evaluation, nothing run yet: one `Setup` per task set (one, or one per task
    seed), the protocol's options and the output folder (None: nothing is written)."""

    setups: list[Setup]
    task_seeds: list[int] | None
    eval_seed: int
    episodes: int | None
    online: bool
    animate: bool
    split_size: int  # the number of tasks of the (first) split
    default_out: Path  # the folder the command writes into when none is given
    out: Path | None = None

    @property
    def setup(self) -> Setup:
        return self.setups[0]

    @property
    def span(self) -> str:
        """The task seeds as text: A-B when consecutive, else A,B,C ('' for one task set)."""
        seeds = self.task_seeds
        if not seeds:
            return ""
        if seeds == list(range(seeds[0], seeds[-1] + 1)):
            return f"{seeds[0]}-{seeds[-1]}"
        return ",".join(map(str, seeds))

    def writing_to(self, out: str | Path, overwrite: bool = False) -> Plan:
        """This plan writing its results.json (and figures) into `out`, checked now (created,
        writable, not a run's folder, no earlier results.json unless `overwrite`)."""
        out = Path(out)
        check_out(out, overwrite)
        setups = [dataclasses.replace(s, out=out) for s in self.setups]
        return dataclasses.replace(self, setups=setups, out=out)

    def run(self, on_task_set: Callable[[int, dict], None] | None = None) -> Evaluation:
        """Run the controller on every task set (`on_task_set(task seed, record)` after each one
        of several), then write results.json (and the figures) when there is an output folder."""
        from mpcpearl_jax.runfolder import write_json

        if self.task_seeds is None:
            s = self.setups[0]
            record, result, stats = run_setup(s, self.eval_seed, self.episodes, self.online)
            ev = Evaluation(record, result, stats, s, self.out)
            if self.out is not None:
                write_json(self.out / "results.json", record)  # before the figures
                ev.written = [self.out / "results.json", *write_figures(s, result, self.animate)]
            return ev
        records, stats = [], None
        for ts, s in zip(self.task_seeds, self.setups, strict=True):
            record, _, stats = run_setup(s, self.eval_seed, self.episodes, self.online)
            records.append(record)
            if on_task_set is not None:
                on_task_set(ts, record)
        summary = pooled_record(self.setups[-1], self.task_seeds, records)
        ev = Evaluation(summary, None, stats, self.setups[-1], self.out)
        if self.out is not None:
            write_json(self.out / "results.json", summary)
            ev.written = [self.out / "results.json"]
        return ev


def evaluate(
    run: str | Path | Any | Sequence[Any] | None = None,
    *,
    on_task_set: Callable[[int, dict], None] | None = None,
    **options: Any,
) -> Evaluation:
    """Evaluate `run` (a run folder, a `LoadedPolicy` or a list of them, one per seed; None for
    GP-MPC alone) with the options of `prepare` (`EvaluationOptions`); writes results.json and
    figures only when `out` is given. Raises EvaluationError (a bad argument, one line naming
    it) before anything runs."""
    return _prepare(run, EvaluationOptions.of(options, "evaluate")).run(on_task_set)


def prepare(run: str | Path | Any | Sequence[Any] | None = None, **options: Any) -> Plan:
    """Resolve and check an evaluation (module doc; the options and their defaults:
    `EvaluationOptions`); nothing runs."""
    return _prepare(run, EvaluationOptions.of(options, "prepare"))


def _prepare(run: Any, o: EvaluationOptions) -> Plan:
    if o.controller not in CONTROLLERS:
        raise EvaluationError(f"{{controller}} {o.controller!r}: one of {', '.join(CONTROLLERS)}")
    if o.task_seeds is not None:
        if o.task_seed is not None:
            raise EvaluationError("give {task_seed} or {task_seeds}, not both")
        if o.figures not in (None, "none") or o.animate:
            raise EvaluationError("{task_seeds} makes no figures (drop {figures}/{animate})")
        hint = " in one evaluation (the project's protocol uses 8: 1-8)"
        text = o.task_seeds.strip() if isinstance(o.task_seeds, str) else o.task_seeds
        seeds = sorted(parse_ranges(text, "task_seeds", MAX_TASK_SEEDS, "task sets", hint))
        plans = [
            _one(run, dataclasses.replace(o, task_seed=ts, figures="none"), several_seeds=True)
            for ts in seeds
        ]
        plan = dataclasses.replace(plans[0], setups=[p.setups[0] for p in plans], task_seeds=seeds)
        first = plan.setups[0].out
        plan.default_out = first.parent / f"{first.name}-seeds{plan.span.replace(',', '_')}"
    else:
        plan = _one(run, o)
        plan.animate = o.animate
    return plan.writing_to(o.out, o.overwrite) if o.out is not None else plan


def _signature(fn: Callable[..., Any], keep: int) -> inspect.Signature:
    """`fn`'s signature with its `**options` spelled out as `EvaluationOptions`' fields (what
    help() and editors show): its first `keep` parameters, then one keyword-only parameter per
    option with its default."""
    head = list(inspect.signature(fn).parameters.values())[:keep]
    fields = [
        inspect.Parameter(
            f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default, annotation=f.type
        )
        for f in dataclasses.fields(EvaluationOptions)
    ]
    return inspect.Signature([*head, *fields], return_annotation=fn.__annotations__["return"])


evaluate.__signature__ = _signature(evaluate, 2)  # type: ignore[attr-defined]
prepare.__signature__ = _signature(prepare, 1)  # type: ignore[attr-defined]


def _policies(run: Any) -> list | None:
    """`run` as a list of loaded policies (None when it is a run folder or None)."""
    from mpcpearl_jax.deploy.policy import LoadedPolicy

    if isinstance(run, LoadedPolicy):
        return [run]
    if isinstance(run, (list, tuple)) and run and all(isinstance(p, LoadedPolicy) for p in run):
        return list(run)
    if run is None or isinstance(run, (str, Path)):
        return None
    raise EvaluationError(
        f"{{run}}: expected a run folder, a LoadedPolicy or a list of them, not "
        f"{type(run).__name__}"
    )


def _one(run: Any, o: EvaluationOptions, several_seeds: bool = False) -> Plan:
    """The plan of one task set."""
    from mpcpearl_jax import algorithms
    from mpcpearl_jax.envs import SPLITS, env_names, load_family, make_env
    from mpcpearl_jax.evaluation.report import run_label
    from mpcpearl_jax.runfolder import load_config

    if o.split not in SPLITS:
        raise EvaluationError(f"{{split}} {o.split!r}: one of {', '.join(SPLITS)}")
    scenarios = Path(o.scenarios) if o.scenarios is not None else None
    o = dataclasses.replace(o, scenarios=scenarios)
    given = _policies(run)
    run_dir = Path(run) if isinstance(run, (str, Path)) else None
    ctrl = o.controller
    cfg = None
    if run_dir is not None:
        if not run_dir.is_dir():
            raise EvaluationError(f"{run_dir}: no such directory")
        setup = algorithms.of_run(run_dir).evaluation_setup
        if setup is not None:  # an algorithm evaluated as trained (GrBAL: its own controller)
            s, n = setup(run_dir, **o.arguments(), several_seeds=several_seeds)
            return Plan([s], None, o.eval_seed, None, o.online, False, n, s.out)
        cfg = load_config(run_dir)  # CheckpointError: not a run directory
    elif given is not None:
        cfg = given[0].config
    elif ctrl != "gp-mpc":
        raise EvaluationError(f"{{controller}} {ctrl} needs a run directory ({{run}})")
    if ctrl == "gp-mpc" and (o.online or o.episodes is not None):
        raise EvaluationError("{online} and {episodes} apply to the policy (GP-MPC does not adapt)")
    if ctrl != "policy" and o.online:
        raise EvaluationError(f"{{online}} applies to {{controller}} policy, not {ctrl}")
    if ctrl == "gp-mpc" and o.eps is not None:
        raise EvaluationError(
            "{eps} applies to {controller} policy+mpc (GP-MPC acts on every step)"
        )
    if ctrl == "policy" and (o.mpc or o.eps is not None or o.preset is not None):
        raise EvaluationError("{mpc} and {eps} apply to the MPC controllers (gp-mpc, policy+mpc)")
    shield_cfg = ShieldConfig() if o.shield is True else (o.shield or None)
    if shield_cfg is not None and not isinstance(shield_cfg, ShieldConfig):
        raise EvaluationError(f"{{shield}}: expected True or a ShieldConfig, got {o.shield!r}")
    if shield_cfg is not None and ctrl != "policy":
        raise EvaluationError(f"{{shield}} applies to {{controller}} policy, not {ctrl}")
    if o.episodes is not None and o.episodes < 0:
        raise EvaluationError(f"{{episodes}} {o.episodes}: must be >= 0")
    if o.online and o.episodes is not None:
        raise EvaluationError(
            "{episodes} counts the adaptation episodes before the scored one; {online} adapts "
            "within the one scored episode: give one of them"
        )
    check_eval_seed(o.eval_seed)
    family = None
    if o.env:
        try:
            family = load_family(o.env)  # MODULE:NAME registers NAME
        except ValueError as e:
            raise EvaluationError(f"{{env}} {e}") from None
    env_name = cfg.env if cfg else (family or "restaurant")
    if cfg and family and family != cfg.env:
        raise EvaluationError(f"{{env}} {o.env}: the run {run_dir} was trained on {cfg.env}")
    data_file = str(o.data) if o.data else (cfg.data if cfg else None)
    if data_file is not None and not Path(data_file).is_file():
        hint = "" if o.data else " (the run's data file; pass {data} PATH)"
        raise EvaluationError(f"data file {data_file} does not exist{hint}")
    overrides = dict(cfg.env_overrides) if cfg else {}
    if cfg and env_name not in env_names():
        raise EvaluationError(
            f"{run_dir}: trained on the task family {env_name!r}, not registered here: pass "
            f"{{env}} MODULE:{env_name}, MODULE the module that registers it "
            "(docs/custom_tasks.md)"
        )
    try:
        env_obj = make_env(env_name, **overrides)
    except ValueError as e:
        raise EvaluationError(str(e)) from e
    ts, options, chosen, task_ids, figure_ids, perturbation, n = task_setup(
        cfg,
        env_obj,
        env_name,
        data_file,
        o.split,
        task_seed=o.task_seed,
        several_seeds=several_seeds,
        scenarios=scenarios,
        tasks=o.tasks,
        figures=o.figures,
        perturb=o.perturb,
    )
    base = cfg.mpc.to_dict() if cfg else None
    mpc_fields = mpc_settings(env_name, base, o.preset, o.mpc) if ctrl != "policy" else {}
    policies: list = []
    seed_ids: list[int] = []
    label, eps_used = "GP-MPC", None
    if ctrl != "gp-mpc":
        assert cfg is not None
        seeds = cfg.seeds if given is None else len(given)
        if o.seed_index is not None and not 0 <= o.seed_index < seeds:
            raise EvaluationError(f"{{seed_index}} {o.seed_index}: the run has {seeds} seed(s)")
        seed_ids = list(range(seeds)) if o.seed_index is None else [o.seed_index]
        if given is not None:
            policies = [given[s] for s in seed_ids]
        else:
            from mpcpearl_jax.deploy.policy import load_policy

            assert run_dir is not None
            try:  # CheckpointError (no or corrupt policy.msgpack) goes to the caller as it is
                policies = [load_policy(run_dir, s) for s in seed_ids]
            except (ValueError, TypeError, OSError) as e:
                raise EvaluationError(f"{run_dir}: cannot load the policy: {e}") from e
        label = run_label(cfg)
        if ctrl == "policy+mpc":
            eps_used = cfg.train.eps if o.eps is None else o.eps
            if not 0.0 <= eps_used <= 1.0:
                raise EvaluationError(f"{{eps}} {eps_used}: must be in [0, 1]")
            label = f"{label} + MPC (eps {eps_used:g})"
        if shield_cfg is not None:
            label += f" + shield (margin {shield_cfg.margin:g} m, lookahead {shield_cfg.lookahead})"
    elif o.seed_index is not None:
        raise EvaluationError("{seed_index} applies to a run's policy, not to gp-mpc")
    if run_dir is not None:
        name = f"{ctrl}-shield" if shield_cfg is not None else ctrl
        where = default_out(run_dir, name, o.split, o.online, options, perturbation)
    else:
        split_name = f"scenarios-{o.split}" if options is not None else o.split
        name = f"{ctrl}-{env_name}-{split_name}{perturbation.folder_suffix}"
        where = Path("runs") / "eval" / name
    s = Setup(
        controller=ctrl,
        env_name=env_name,
        env_config=env_obj.config,
        split=o.split,
        task_seed=ts,
        data=data_file,
        tasks=chosen,
        task_ids=task_ids,
        figure_ids=figure_ids,
        out=where,
        label=label,
        run=run_dir,
        run_config=cfg,
        policies=policies,
        seed_ids=seed_ids,
        mpc=mpc_fields,
        eps=eps_used,
        shield=shield_cfg,
        scenarios=options,
        perturbation=perturbation.label,
    )
    return Plan([s], None, o.eval_seed, o.episodes, o.online, False, n, where)
