"""The expert's convergence curve: how far the MPC's SQP (paper eq. (4), method §6) stops from the
optimum of its own problem, what that costs in closed loop, and what a solve costs, side by side.

For each SQP setting of `SETTINGS` (iteration cap and step tolerance, extra starts, recovery):

- `problems`: on the problems recorded from training (`tests/data/mpc_problems.npz`), the exact
  SAA merit's gap to the best plan known (the SQP run to convergence with tight QPs from every
  start of `problem.START_NAMES`, the lowest merit kept), the share of problems more than 1 % above
  it, the share whose first input lies within 0.02 of the best plan's, and the solve time;
- `scenarios`: GP-MPC (the MPC acting at every step) on all 205 of the authors' restaurant
  scenarios (180 training + 25 test), SR and CFR with 95 % Wilson intervals over the tasks, the
  solve time per row (median, p95), fallbacks and their longest run in an episode, and why each
  SQP ended;
- `figure`: merit gap and SR against the median solve time per row.

    python -m lab.convergence problems [--count 48]
    python -m lab.convergence scenarios --scenarios ../shared/data/mpc-pearl-scenarios [--only NAME]
    python -m lab.convergence figure

Records: results/mpc/convergence/*.json (one file per part and setting), figure convergence.png.
The records `device-problems-*.json` are those of the device solver, since removed (docs/method.md
§6).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from mpcpearl_jax.cli.stopping import stops_with

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "results" / "mpc" / "convergence"
PROBLEMS = ROOT / "tests" / "data" / "mpc_problems.npz"

# name -> MPCConfig fields (over the MPCConfig defaults; unsafe_recovery off unless named), in
# the order they are measured. "converged": a step below 1e-4 or no decrease along the QP's
# direction (the line search fails: stationary up to the QPs' accuracy), capped at 100 QPs
SETTINGS: dict[str, dict] = {
    "2 it": dict(sqp_iters=2, sqp_step_tol=0.05),
    "5 it": dict(sqp_iters=5, sqp_step_tol=1e-3),
    "10 it": dict(sqp_iters=10, sqp_step_tol=1e-3),
    "converged": dict(sqp_iters=100, sqp_step_tol=1e-4),
    "3 it": dict(sqp_iters=3, sqp_step_tol=1e-3),
    "8 it": dict(sqp_iters=8, sqp_step_tol=1e-3),
    "2 it, restart": dict(sqp_iters=2, sqp_step_tol=0.05, multi_start="on_failure"),
    "5 it, restart": dict(sqp_iters=5, sqp_step_tol=1e-3, multi_start="on_failure"),
    "5 it, ls 8, restart": dict(
        sqp_iters=5, sqp_step_tol=1e-3, line_search_steps=8, multi_start="on_failure"
    ),
    "converged, restart": dict(sqp_iters=100, sqp_step_tol=1e-4, multi_start="on_failure"),
    "converged, multi-start": dict(sqp_iters=100, sqp_step_tol=1e-4, multi_start="always"),
    "converged, grid": dict(sqp_iters=100, sqp_step_tol=1e-4, unsafe_recovery=True),
    # the grid recovery (`unsafe_recovery`, the learned presets' MPC) at fewer QPs
    "2 it, grid": dict(sqp_iters=2, sqp_step_tol=0.05, unsafe_recovery=True),
    "5 it, grid": dict(sqp_iters=5, sqp_step_tol=1e-3, unsafe_recovery=True),
    "5 it, restart, grid": dict(
        sqp_iters=5, sqp_step_tol=1e-3, multi_start="on_failure", unsafe_recovery=True
    ),
    # a longer line search (step sizes down to 1/128): fewer stalls on the nonsmooth merit
    "converged, ls 8": dict(sqp_iters=100, sqp_step_tol=1e-4, line_search_steps=8),
    "converged, ls 8, restart": dict(
        sqp_iters=100, sqp_step_tol=1e-4, line_search_steps=8, multi_start="on_failure"
    ),
}
# the best plan known on a recorded problem: the SQP to convergence, tight QPs, every start
REFERENCE = dict(
    sqp_iters=60,
    sqp_step_tol=1e-6,
    multi_start="always",
    line_search_steps=8,
    osqp_eps_abs=1e-5,
    osqp_eps_rel=1e-5,
    osqp_max_iter=4000,
)
FIRST_INPUT_TOL = 0.02


def slug(name: str) -> str:
    return name.replace(", ", "-").replace(" ", "")


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a rate k / n."""
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (max(0.0, c - h), min(1.0, c + h))


def _write(path: Path, record: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(record, indent=1))
    tmp.replace(path)
    print(f"wrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}", flush=True)


# ----------------------------------------------------------------------------- recorded problems
def _load_problems(count: int):
    from mpcpearl_jax.mpc import recorded

    rec = recorded.load(PROBLEMS)
    ids = np.linspace(0, len(rec) - 1, min(count, len(rec))).round().astype(int)
    return rec, [(int(i), *rec.row(i)) for i in ids]


def _solver(rec, fields: dict):
    """The SQP on the recorded problems' params and OSQP settings, MPCConfig-named fields
    replaced (`osqp_*` in OSQP's settings)."""
    from mpcpearl_jax.mpc.sqp import SQPSolver

    osqp_keys = {
        "osqp_eps_abs": "eps_abs",
        "osqp_eps_rel": "eps_rel",
        "osqp_max_iter": "max_iter",
        "osqp_polish": "polishing",
    }
    qp = {osqp_keys[k]: v for k, v in fields.items() if k in osqp_keys}
    plain = {"unsafe_recovery": False, "multi_start": "off"}
    plain.update({k: v for k, v in fields.items() if k not in osqp_keys})
    return SQPSolver(dataclasses.replace(rec.params, **plain), dataclasses.replace(rec.qp, **qp))


def part_problems(args) -> None:
    rec, rows = _load_problems(args.count)
    ref_solver = _solver(rec, REFERENCE)
    t0 = time.perf_counter()
    ref = [ref_solver.solve(row, init) for _, row, init in rows]
    print(f"reference on {len(rows)} problems: {time.perf_counter() - t0:.1f} s", flush=True)
    ref_merit = np.array([r.merit for r in ref])
    ref_first = np.array([r.u[0] for r in ref])
    out = {
        "problems": [i for i, _, _ in rows],
        "reference": {
            "fields": REFERENCE,
            "merit": ref_merit.tolist(),
            "start": [r.start for r in ref],
            "stop": [r.stop for r in ref],
            "first": ref_first.tolist(),
        },
        "settings": {},
    }
    for name in _selected(args):
        solver = _solver(rec, SETTINGS[name])
        with _CPUClock() as clock:
            res = [solver.solve(row, init) for _, row, init in rows]
        out["settings"][name] = _problem_stats(SETTINGS[name], res, ref_merit, ref_first)
        out["settings"][name].update(_cpu_stats(clock.cpu_s))
        s = out["settings"][name]
        print(
            f"{name:24s} gap median {100 * s['gap_median']:6.2f} %  "
            f">1 %: {s['share_gap_over_1pct']:.2f}  "
            f"first input within {FIRST_INPUT_TOL}: {s['share_first_close']:.2f}  "
            f"solve median {s['solve_ms_median']:.2f} ms p95 {s['solve_ms_p95']:.2f}",
            flush=True,
        )
    out["count"] = len(rows)
    path = OUT / "problems.json"
    if args.only and path.exists():  # add to the settings measured before on the same problems
        before = json.loads(path.read_text())
        if before["problems"] == out["problems"]:
            out["settings"] = {**before["settings"], **out["settings"]}
    _write(path, out)


def _problem_stats(fields, res, ref_merit, ref_first) -> dict:
    merit = np.array([float(r.merit) for r in res])
    first = np.array([np.asarray(r.u)[0] for r in res])
    gap = (merit - ref_merit) / np.maximum(np.abs(ref_merit), 1e-9)
    close = np.max(np.abs(first - ref_first), axis=1) <= FIRST_INPUT_TOL
    ms = 1e3 * np.array([r.solve_time for r in res])
    stops: dict[str, int] = {}
    for r in res:
        stops[r.stop] = stops.get(r.stop, 0) + 1
    return {
        "fields": fields,
        "gap_median": float(np.median(gap)),
        "gap_mean": float(np.mean(gap)),
        "gap_p90": float(np.percentile(gap, 90)),
        "share_gap_over_1pct": float(np.mean(gap > 0.01)),
        "share_first_close": float(np.mean(close)),
        "share_ok": float(np.mean([bool(r.ok) for r in res])),
        "solve_ms_median": float(np.median(ms)),
        "solve_ms_mean": float(np.mean(ms)),
        "solve_ms_p95": float(np.percentile(ms, 95)),
        "n_qp_mean": float(np.mean([int(r.n_qp) for r in res])),
        "stops": stops,
        "gap": gap.tolist(),
    }


# ----------------------------------------------------------------------------- the 205 scenarios
def _scenario_tasks(env, directory: Path, splits=("train", "test")):
    import jax

    from mpcpearl_jax.envs.restaurant.scenarios import make_scenario_tasks

    parts = [make_scenario_tasks(s, env.config, directory) for s in splits]
    return jax.tree_util.tree_map(lambda *a: np.concatenate([np.asarray(x) for x in a]), *parts)


class _CPUClock:
    """Records the CPU time of the solving thread of every `SQPSolver.solve` (time.thread_time:
    what the solve costs, whatever else shares the machine), beside the solver's wall time."""

    def __init__(self):
        self.cpu_s: list[float] = []

    def __enter__(self):
        from mpcpearl_jax.mpc import sqp

        self._orig = orig = sqp.SQPSolver.solve
        clock = self

        def timed(self_, *a, **kw):
            t0 = time.thread_time()
            res = orig(self_, *a, **kw)
            clock.cpu_s.append(time.thread_time() - t0)
            return res

        sqp.SQPSolver.solve = timed
        return self

    def __exit__(self, *exc):
        from mpcpearl_jax.mpc import sqp

        sqp.SQPSolver.solve = self._orig


def _cpu_stats(cpu_s) -> dict:
    ms = 1e3 * np.asarray(cpu_s)
    if not ms.size:
        return {"solve_cpu_ms_median": None, "solve_cpu_ms_mean": None, "solve_cpu_ms_p95": None}
    return {
        "solve_cpu_ms_median": float(np.median(ms)),
        "solve_cpu_ms_mean": float(np.mean(ms)),
        "solve_cpu_ms_p95": float(np.percentile(ms, 95)),
    }


def gp_mpc_record(env, tasks, cfg, sample_seed: int = 0) -> dict:
    """GP-MPC on a batch of tasks with MPCConfig cfg: task-level results, solve statistics."""
    with _CPUClock() as clock:
        rec = _gp_mpc_record(env, tasks, cfg, sample_seed)
    rec.update(_cpu_stats(clock.cpu_s))
    return rec


def _gp_mpc_record(env, tasks, cfg, sample_seed: int = 0) -> dict:
    import jax

    from mpcpearl_jax.evaluation import metrics
    from mpcpearl_jax.mpc import (
        FALLBACK_PLAN,
        FALLBACK_POLICY,
        make_gp_mpc_rollout,
        make_mpc_bridge,
    )

    bridge = make_mpc_bridge(env, cfg)
    t0 = time.perf_counter()
    traj = jax.jit(make_gp_mpc_rollout(env, bridge))(jax.random.PRNGKey(sample_seed), tasks)
    traj = jax.tree_util.tree_map(np.asarray, jax.block_until_ready(traj))
    wall = time.perf_counter() - t0
    bridge.close()
    stats = bridge.stats()
    ep = metrics.episode_metrics(
        traj["position"],
        traj["collision"],
        traj["in_goal"],
        np.asarray(tasks.goal),
        env.config.robot_radius,
    )
    success = np.asarray(ep.success, bool)
    free = np.asarray(ep.collision_free, bool)
    fb = np.isin(traj["status"], (FALLBACK_PLAN, FALLBACK_POLICY))
    longest = [_longest_run(row) for row in fb]
    n = success.size
    solve_ms = 1e3 * np.asarray(stats["solve_s"])
    return {
        "tasks": n,
        "SR": float(success.mean()),
        "SR_ci95": wilson(int(success.sum()), n),
        "CFR": float(free.mean()),
        "CFR_ci95": wilson(int(free.sum()), n),
        "TT": float(np.mean(ep.travel_time)),
        "SPL": float(np.mean(ep.spl)),
        "success": success.astype(int).tolist(),
        "collision_free": free.astype(int).tolist(),
        "fallback_share": float(fb.mean()),
        "fallback_longest_run_max": int(max(longest)),
        "fallback_longest_run": longest,
        "solve_ms_median": float(np.median(solve_ms)) if solve_ms.size else None,
        "solve_ms_mean": float(np.mean(solve_ms)) if solve_ms.size else None,
        "solve_ms_p95": float(np.percentile(solve_ms, 95)) if solve_ms.size else None,
        "n_qp_mean": float(np.mean(stats["n_qp"])) if stats["n_qp"] else None,
        "status": stats["status"],
        "reasons": stats["reasons"],
        "sqp_stops": stats.get("sqp_stops", {}),
        "starts": stats.get("starts", {}),
        "wall_s": wall,
    }


def _longest_run(flags: np.ndarray) -> int:
    best = cur = 0
    for f in flags:
        cur = cur + 1 if f else 0
        best = max(best, cur)
    return best


def _env_and_base():
    from mpcpearl_jax.envs import make_env, mpc_defaults
    from mpcpearl_jax.mpc import MPCConfig

    env = make_env("restaurant")
    return env, MPCConfig(**mpc_defaults("restaurant"))


def part_scenarios(args) -> None:
    env, base = _env_and_base()
    tasks = _scenario_tasks(env, args.scenarios)
    for name in _selected(args):
        path = OUT / f"scenarios-{slug(name)}.json"
        if path.exists() and not args.redo:
            print(f"{name}: {path.name} exists (--redo to measure again)")
            continue
        fields = {"unsafe_recovery": False, "multi_start": "off", **SETTINGS[name]}
        cfg = base.replace(**fields)
        rec = gp_mpc_record(env, tasks, cfg, args.sample_seed)
        rec.update(
            name=name,
            fields=fields,
            mpc=cfg.to_dict(),
            sample_seed=args.sample_seed,
            split="train (0-179) + test (180-204)",
        )
        _print_row(name, rec)
        _write(path, rec)


def _print_row(name, rec) -> None:
    lo, hi = rec["SR_ci95"]
    print(
        f"{name:24s} SR {rec['SR']:.3f} [{lo:.2f}, {hi:.2f}]  CFR {rec['CFR']:.3f}  "
        f"solve median {rec['solve_ms_median']:.2f} ms p95 {rec['solve_ms_p95']:.2f} "
        f"(CPU {rec['solve_cpu_ms_median']:.2f} / {rec['solve_cpu_ms_p95']:.2f})  "
        f"fallbacks {100 * rec['fallback_share']:.1f} % (longest {rec['fallback_longest_run_max']})"
        f"  stops {rec['sqp_stops']}  {rec['wall_s']:.0f} s",
        flush=True,
    )


# ----------------------------------------------------------------------------- table and figure
def part_figure(args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    probs = json.loads((OUT / "problems.json").read_text())["settings"]
    scen = {}
    for name in SETTINGS:
        p = OUT / f"scenarios-{slug(name)}.json"
        if p.exists():
            scen[name] = json.loads(p.read_text())
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, s in probs.items():
        x = s.get("solve_cpu_ms_median", s["solve_ms_median"])
        a.scatter(x, 100 * s["gap_median"])
        a.annotate(name, (x, 100 * s["gap_median"]), fontsize=7)
    a.set_yscale("log")
    a.set_xlabel("solve per problem, CPU ms, median")
    a.set_ylabel("merit above the best plan known, median (%)")
    a.set_title(f"{len(probs and next(iter(probs.values()))['gap'])} recorded problems")
    for name, r in scen.items():
        lo, hi = r["SR_ci95"]
        x = r["solve_cpu_ms_mean"]
        b.errorbar(x, r["SR"], yerr=[[r["SR"] - lo], [hi - r["SR"]]], fmt="o", capsize=2)
        b.annotate(name, (x, r["SR"]), fontsize=7)
    b.set_xlabel("solve per row, CPU ms, mean")
    b.set_ylabel("GP-MPC SR (95 % interval)")
    b.set_title("GP-MPC on the 205 restaurant scenarios")
    fig.tight_layout()
    fig.savefig(OUT / "convergence.png", dpi=120)
    print(f"wrote {OUT / 'convergence.png'}")
    text = table(probs, scen)
    print(text)
    _into_docs(text)


METHOD_DOC = ROOT / "docs" / "method.md"
_MARKS = (
    "<!-- convergence table: python -m lab.convergence figure -->\n",
    "\n<!-- /convergence table -->",
)


def _into_docs(text: str) -> None:
    """The table into docs/method.md §6, between its marker comments."""
    doc = METHOD_DOC.read_text()
    head, tail = _MARKS
    if head not in doc or tail not in doc:
        return
    a, b = doc.index(head) + len(head), doc.index(tail)
    METHOD_DOC.write_text(doc[:a] + text + doc[b:])
    print(f"wrote the table into {METHOD_DOC.relative_to(ROOT)}")


def table(probs: dict, scen: dict) -> str:
    """The curve as a Markdown table: merit gap on the recorded problems; GP-MPC on the 205
    scenarios (95 % Wilson intervals), on the 180 training and the 25 test ones; fallbacks; the
    solve's CPU time per row."""
    head = (
        "| SQP | merit gap, median | gap > 1 % | first input within 0.02 | SR, 205 | CFR, 205 "
        "| SR / CFR, 180 train | SR / CFR, 25 test | fallbacks | solve CPU ms, median / mean / "
        "p95 |"
    )
    lines = [head, "|" + "---|" * 10]
    for name in SETTINGS:
        p, r = probs.get(name), scen.get(name)
        cells = [name]
        if p:
            cells += [
                f"{100 * p['gap_median']:.2f} %",
                f"{p['share_gap_over_1pct']:.2f}",
                f"{p['share_first_close']:.2f}",
            ]
        else:
            cells += ["-"] * 3
        if r:
            sr, cf = np.asarray(r["success"]), np.asarray(r["collision_free"])
            cells += [
                f"{r['SR']:.3f} [{r['SR_ci95'][0]:.2f}, {r['SR_ci95'][1]:.2f}]",
                f"{r['CFR']:.3f} [{r['CFR_ci95'][0]:.2f}, {r['CFR_ci95'][1]:.2f}]",
                f"{sr[:180].mean():.3f} / {cf[:180].mean():.3f}",
                f"{sr[180:].mean():.2f} / {cf[180:].mean():.2f}",
                f"{100 * r['fallback_share']:.1f} %",
                f"{r['solve_cpu_ms_median']:.1f} / {r['solve_cpu_ms_mean']:.1f} / "
                f"{r['solve_cpu_ms_p95']:.1f}",
            ]
        else:
            cells += ["-"] * 6
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _selected(args) -> list[str]:
    names = args.only or list(SETTINGS)
    unknown = [n for n in names if n not in SETTINGS]
    if unknown:
        raise SystemExit(f"error: --only {unknown[0]!r}: unknown setting; known: {list(SETTINGS)}")
    return names


@stops_with("stopped: the parts already measured are saved (one file each)")
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m lab.convergence", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("part", choices=("problems", "scenarios", "figure"))
    ap.add_argument("--count", type=int, default=48, help="recorded problems, evenly spread")
    ap.add_argument(
        "--scenarios", type=Path, default=ROOT.parent / "shared" / "data" / "mpc-pearl-scenarios"
    )
    ap.add_argument("--sample-seed", type=int, default=0)
    ap.add_argument("--only", action="append", help="one setting of SETTINGS (repeatable)")
    ap.add_argument("--redo", action="store_true", help="measure settings already recorded again")
    args = ap.parse_args(argv)
    if args.count < 1:  # before any problem is read
        print(f"error: --count must be positive, got {args.count}", file=sys.stderr)
        return 2
    {
        "problems": part_problems,
        "scenarios": part_scenarios,
        "figure": part_figure,
    }[args.part](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
