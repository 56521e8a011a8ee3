"""The summary tables at the top of README.md and results/README.md: this project against the
paper on the paper's own 25 test scenarios with the training budgets beside the scores, the
main command over its ten seeds, the crowd perturbations of the headline runs, and the speed of
the CPU and GPU machines (from `benchmarks/results/`). Built on `render`'s cells."""

from __future__ import annotations

from collections.abc import Sequence

from lab.tables.catalogue import (
    GP_MPC,
    GP_MPC_CONVERGED,
    GP_MPC_EXPERT,
    MAIN_PASS,
    MAIN_SEED_SUMMARY,
    PERTURBATIONS,
    RECIPE_MPC_PEARL,
    ROBUSTNESS,
    ROBUSTNESS_CHOICE,
    SEED_GROUPS,
    Entry,
)
from lab.tables.render import (
    _minutes,
    fmt_count,
    fmt_metric,
    render_perturbed,
)
from lab.tables.statistics import MISSING, NO_RECORD, Records, entry_values
from mpcpearl_jax.evaluation.report import PAPER_TRAINING, paper_training

# ---------------------------------------------------------------- budgets


def _thousands(x: float) -> str:
    return f"{int(round(x)):,}"


def run_budget(rec: Records, e: Entry) -> str:
    """'24 min each on a 2-core CPU, 59,500-80,000 gradient steps, 5 seeds' from the runs'
    curve.json (or metrics.jsonl): wall-clock minutes, the cores their records name, steps."""
    minutes = fmt_count(entry_values(rec, e, "budget", ""), _minutes)
    steps = fmt_count(entry_values(rec, e, "grad_steps", ""), _thousands)
    if MISSING in (minutes, steps):
        return MISSING
    cores = set()
    for run in e.runs:  # the machine of the learning harness's curve.json, else of results.json
        has_curve = (rec.results / run / "curve.json").is_file()
        record = rec.read(f"{run}/curve.json" if has_curve else f"{run}/results.json")
        cores.add((record or {}).get("machine", {}).get("cores_available"))
    known = len(cores) == 1 and None not in cores
    where = f"a {cores.pop()}-core CPU" if known else "a CPU (cores not recorded)"
    seeds = f", {len(e.runs)} seeds" if len(e.runs) > 1 else ", 1 seed"
    each = " each" if len(e.runs) > 1 else ""
    return f"{minutes} min{each} on {where}, {steps} gradient steps{seeds}"


def _paper_budget(method: str) -> str:
    if method == "MPC-PEARL 0.2":
        return paper_training("restaurant")
    if method == "GP-MPC":
        return "no training"
    return f"mean over {PAPER_TRAINING['restaurant']['seeds']} seeds; training time not reported"


# ---------------------------------------------------------------- README: against the paper

SUMMARY_METRICS = ("SR", "CFR", "TT", "SPL")
RECIPE = Entry("MPC-PEARL 0.2, this project's recipe", RECIPE_MPC_PEARL)


def render_summary(rec: Records) -> str:
    """README's first table: the paper's MPC-PEARL 0.2 and GP-MPC, this project's recipe over
    its five seeds and its GP-MPC, on the paper's 25 test scenarios, with each one's training;
    then the main command over seeds 0-9."""
    rows = [
        (Entry("MPC-PEARL 0.2, the paper", paper="MPC-PEARL 0.2"), _paper_budget("MPC-PEARL 0.2")),
        (RECIPE, run_budget(rec, RECIPE)),
        (Entry("GP-MPC, the paper", paper="GP-MPC"), _paper_budget("GP-MPC")),
        (
            Entry(
                "GP-MPC, this project, the SQP to convergence (the `paper` preset's expert)",
                files=GP_MPC_CONVERGED.files,
            ),
            "no training",
        ),
        (
            Entry(
                "GP-MPC, this project, 2 QPs without the unsafe-plan recovery", files=GP_MPC.files
            ),
            "no training",
        ),
        (
            Entry(
                "GP-MPC, this project, the learned presets' expert (2 QPs with the unsafe-plan "
                "recovery)",
                files=GP_MPC_EXPERT.files,
            ),
            "no training",
        ),
    ]
    head = ["", *SUMMARY_METRICS, "training"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for e, budget in rows:
        cells = [fmt_metric(entry_values(rec, e, "scen_test", m), m) for m in SUMMARY_METRICS]
        lines.append(f"| {e.label} | " + " | ".join(cells) + f" | {budget} |")
    lines += [
        "",
        "On the paper's 25 test scenarios after two adaptation episodes (`python -m "
        "experiments.evaluate RUN --scenarios DIR`; SR, CFR, SPL: higher is better; TT: steps "
        "of the episode not spent at the goal, lower is better); this project's recipe: mean +- "
        "standard error over its five seeds (worst seed), each trained by `python -m "
        "experiments.restaurant --preset recipe --eps 0.2 --minutes 24 --seed S` (records, the "
        "folders under `results/` these numbers are read from: "
        + ", ".join(f"`{r}`" for r in RECIPE.runs)
        + "); GP-MPC: the MPC alone at every step, `python -m experiments.gp_mpc --scenarios DIR "
        "--split test`: with the MPC settings of the `paper` preset (the default), its SQP run to "
        "convergence; with 2 QPs per solve and no unsafe-plan recovery; and with `--preset "
        "default`, the expert the learned presets (`default`, `recipe`, `cpu-explore`) train "
        "with: 2 QPs per solve and the unsafe-plan recovery (docs/method.md §6); the paper: its "
        "published table.",
        "",
        _main_command_line(rec),
    ]
    return "\n".join(lines)


def _main_command_line(rec: Records) -> str:
    """The main command (`default`) over seeds 0-9 in one sentence: its command, the training
    time range (the first iteration's compilation included, from metrics.jsonl's wall clock)
    and SR's distribution over the seeds."""
    name, runs = MAIN_SEED_SUMMARY[0]
    e = Entry(name, tuple(runs))
    test, val = entry_values(rec, e, "test", "SR"), entry_values(rec, e, "val8", "SR")
    budget = fmt_count(entry_values(rec, e, "budget", ""), _minutes)
    logs = [rec.read(f"{run}/metrics.jsonl") for run in runs]
    if isinstance(test, str) or isinstance(val, str) or budget == MISSING or None in logs:
        return f"The main command: {MISSING}"
    first = sorted(float(rows[0]["wall_s"]) for rows in logs)  # the first iteration: compiles
    pairs = zip(test, val, strict=True)
    passed = sum(t.value >= MAIN_PASS and v.value >= MAIN_PASS for t, v in pairs)
    per_seed = " ".join(f"{t.value:.2f}" for t in test)
    return (
        f"The main command, `python -m experiments.restaurant` (preset `default`, 75 "
        f"iterations), over seeds 0-{len(runs) - 1} (`--seed S`) on a 2-core CPU: training took "
        f"{budget} min, of which the first iteration, which compiles, {first[0]:.0f}-"
        f"{first[-1]:.0f} s (start-up and the final evaluation come on top); test SR "
        f"{fmt_metric(test, 'SR')} (per seed: {per_seed}) on the 24 test tasks and "
        f"{fmt_metric(val, 'SR')} on the 192 validation tasks; {passed} of {len(runs)} seeds "
        f"reach SR {MAIN_PASS} on both."
    )


# ---------------------------------------------------------------- results/README: side by side

PAPER_METRICS = ("SR", "CFR", "TT", "SPL", "MGD")
# method in the paper's table -> this project's seed group of the same name (SEED_GROUPS)
SIDE_BY_SIDE = (
    ("MPC-PEARL 0.2", "MPC-PEARL 0.2"),
    ("PEARL", "PEARL"),
    ("MPC-SAC", "MPC-SAC 0.2"),
    ("GP-MPC", None),
    (None, "GrBAL"),
)
# further rows of a method: source, run folders (trained on the paper's own training scenarios)
SIDE_BY_SIDE_MORE = {
    "MPC-PEARL 0.2": (
        (
            "this project, `cpu-explore` trained on the paper's scenarios 0-149",
            ("restaurant/paper-scenarios/cpu-explore-eps0.2",),
        ),
    ),
}


def render_paper(rec: Records, groups: Sequence[tuple[str, Sequence[str]]] = SEED_GROUPS) -> str:
    """The paper's table beside this project's five seeds per method (and its GP-MPC), on the
    paper's 25 test scenarios, with each row's training."""
    seeds = {name: Entry(name, tuple(runs)) for name, runs in groups}
    head = ["method", "source", *PAPER_METRICS, "training"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for paper, ours in SIDE_BY_SIDE:
        name = paper or ours
        rows: list[tuple[str, Entry | None, str]] = []
        if paper is not None:
            rows.append(("the paper", Entry(name, paper=paper), _paper_budget(paper)))
        else:
            rows.append(("the paper", None, "not in the paper's table"))
        if ours is None:
            rows.append(("this project", Entry(name, files=GP_MPC_CONVERGED.files), "no training"))
            rows.append(
                (
                    "this project, 2 QPs without the unsafe-plan recovery",
                    Entry(name, files=GP_MPC.files),
                    "-",
                )
            )
            rows.append(
                (
                    "this project, the learned presets' expert (2 QPs with the unsafe-plan "
                    "recovery)",
                    Entry(name, files=GP_MPC_EXPERT.files),
                    "-",
                )
            )
        else:
            rows.append(("this project", seeds[ours], run_budget(rec, seeds[ours])))
        for source, runs in SIDE_BY_SIDE_MORE.get(name, ()):
            e = Entry(source, runs)
            rows.append((source, e, run_budget(rec, e)))
        for i, (source, e, budget) in enumerate(rows):
            cells = [
                NO_RECORD if e is None else fmt_metric(entry_values(rec, e, "scen_test", m), m)
                for m in PAPER_METRICS
            ]
            lines.append("| " + " | ".join([name if i == 0 else "", source, *cells, budget]) + " |")
    lines += [
        "",
        "The paper's 25 test scenarios after two adaptation episodes, the paper's protocol. This "
        "project: mean +- standard error over seeds (worst seed), each seed trained alone on the "
        "generated crowds for the budget shown with `--preset recipe` (GrBAL: `--preset cpu`), so "
        "the paper's scenarios are unseen crowds; one run of `cpu-explore` trained on the paper's "
        "own training scenarios instead "
        "(`restaurant/paper-scenarios/cpu-explore-eps0.2`); GP-MPC: "
        "`gp_mpc/converged/scenarios/restaurant_test.json` (the SQP to convergence), "
        "`gp_mpc/scenarios/restaurant_test.json` (2 QPs) and "
        "`gp_mpc/teacher/scenarios/restaurant_test.json` (2 QPs with the unsafe-plan recovery, "
        "`--preset default`). The paper: its published table "
        "(`mpcpearl_jax.evaluation.report.PAPER`, the training from method §9).",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------- results/README: robustness


def render_robustness_summary(rec: Records) -> str:
    """The crowd perturbations of the three 60-minute runs of the headline preset, the run
    trained with randomised crowd timing, and GP-MPC (the full table is in the research log)."""
    rows = [*ROBUSTNESS, ROBUSTNESS_CHOICE[1], ("GP-MPC", "GP-MPC")]
    lines = render_perturbed(rec, rows, PERTURBATIONS)
    lines += [
        "",
        "SR / CFR on the 192 validation tasks with every person's timing perturbed on an "
        "unchanged path: delay K holds everyone at the start K more steps, speed S walks the "
        "paths S times as fast (docs/method.md §8a). One seed each. Every other committed policy: "
        'docs/research-log.md, "Crowd perturbations".',
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------- speed, CPU and GPU

BENCH = {"cpu": "../benchmarks/results", "gpu": "../benchmarks/results/gpu-h100"}


def _sig(x: float) -> str:
    """Three significant digits, trailing zeros kept (16.0, 0.274, 134)."""
    return f"{x:#.3g}".rstrip(".")


def _rate(x: float) -> str:
    for div, unit in ((1e6, "M"), (1e3, "k")):
        if x >= div:
            return f"{_sig(x / div)}{unit}"
    return _sig(x)


def _duration(s: float) -> str:
    for div, unit in ((1.0, "s"), (1e-3, "ms")):
        if s >= div or (unit == "s" and s >= 0.1):
            return f"{_sig(s / div)} {unit}"
    return f"{_sig(s * 1e6)} us"


def _best(rows: list[dict]) -> str:
    top = max(rows, key=lambda r: r["steps_per_s"])
    return f"{_rate(top['steps_per_s'])}/s (batch {top['batch']})"


def _speed_cells(rec: Records, where: str) -> list[str] | None:
    env = rec.read(f"{BENCH[where]}/env_throughput.json")
    step = rec.read(f"{BENCH[where]}/pearl_step.json")
    it = rec.read(f"{BENCH[where]}/iteration.json")
    lat = rec.read(f"{BENCH[where]}/policy_latency.json")
    if None in (env, step, it, lat):
        return None
    e, s = env["results"], step["results"]
    act = next(r for r in lat["results"]["rows"] if r["call"] == "act" and r["batch"] == 1)
    summ = it["results"]["summary"]
    return [
        _best(e["jax_env"]),
        _best(e["jax_policy"]),
        f"{_duration(s['step']['jax']['median_s'])} (PyTorch on the same machine: "
        f"{_duration(s['step']['torch']['median_s'])})",
        f"{_duration(summ['iteration_scaled_to_750_updates_s'])} (updates "
        f"{_duration(summ['updates_scaled_to_750_s'])})",
        _duration(lat["results"]["mpc"]["call"]["median_s"]),
        _duration(act["latency_us"] * 1e-6),
    ]


SPEED_ROWS = (
    "restaurant env, random actions (`scan` + `vmap`), best batch",
    "env + 3 x 300 policy in the loop, best batch",
    "PEARL gradient step, the paper's sizes (median)",
    "`paper`-preset iteration, eps 0.2, scaled to 750 updates",
    "one MPC call (GP + SQP on the host, median)",
    "trained policy, `load_policy` then `act`, batch 1 (median)",
)


# the GPU session's training figures (`bash benchmarks/gpu_session.sh`, summarised by
# `benchmarks.gpu_summary`): the newest committed benchmarks/results/gpu-*/summary.json that has
# them; "not yet measured" while none is committed
GPU_SESSION = "gpu-*/summary.json"
GPU_SESSION_ROWS = {  # target name in the summary -> the row's label
    "recipe_s": "`recipe` preset, 8 seeds, eps 0.2: seconds per iteration (the faster of the "
    "runs with and without `train.pipeline`)",
    "default_speedup": "`default` preset (the main command's), one seed: the GPU's speed-up per "
    "iteration over the same machine's CPU",
    "paper_s": "`paper` preset, one seed, eps 0.2: seconds per iteration",
}
GPU_SESSION_TARGETS = {"recipe_s": "<= 1.5 s", "default_speedup": ">= 2x", "paper_s": "<= 1.5 s"}
NOT_MEASURED = "not yet measured"


def gpu_session_record(rec: Records) -> tuple[str, dict] | None:
    """(folder under benchmarks/results, summary) of the newest GPU session record, or None."""
    found = []
    for path in (rec.results / BENCH["cpu"]).glob(GPU_SESSION):
        summary = rec.read(f"{BENCH['cpu']}/{path.parent.name}/summary.json")
        if isinstance(summary, dict) and summary.get("targets"):
            found.append((summary.get("written", ""), path.parent.name, summary))
    if not found:
        return None
    _, folder, summary = max(found, key=lambda f: f[:2])
    return folder, summary


def _gpu_session_cells(target: dict) -> tuple[str, str]:
    """(figure, target) cells of one of the GPU session's targets."""
    fig = target.get("figure")
    if fig is None:
        return NOT_MEASURED, target["target"]
    verdict = f"{target['target']}: {'met' if target['met'] else 'not met'}"
    if target["name"] == "default_speedup":
        return (
            f"{fig:.2f}x (GPU {_duration(target['gpu_s'])}, CPU {_duration(target['cpu_s'])})",
            verdict,
        )
    run = {"recipe-pipeline": " (with `train.pipeline`)", "recipe": " (without `train.pipeline`)"}
    return f"{_duration(fig)}{run.get(target.get('run') or '', '')}", verdict


def render_gpu_session(rec: Records) -> list[str]:
    """The lines of the GPU session's training figures against their targets."""
    found = gpu_session_record(rec)
    targets = {t["name"]: t for t in (found[1]["targets"] if found else [])}
    gpu = ((found[1].get("machine") or {}).get("gpu") if found else None) or "one GPU"
    lines = [
        "",
        f"Training on {gpu} (`bash benchmarks/gpu_session.sh`; the median over iterations 3 to "
        "the last, as `python -m benchmarks.gpu_summary` computes it):",
        "",
        "| what | figure | target |",
        "|---|---|---|",
    ]
    for name, what in GPU_SESSION_ROWS.items():
        t = targets.get(name)
        figure, target = _gpu_session_cells(t) if t else (NOT_MEASURED, GPU_SESSION_TARGETS[name])
        lines.append(f"| {what} | {figure} | {target} |")
    lines += [
        "",
        f"Record: `benchmarks/results/{found[0]}/`."
        if found
        else "No training session of `gpu_session.sh` is recorded yet (its records go to "
        "`benchmarks/results/gpu-*/summary.json`).",
    ]
    return lines


def render_speed(rec: Records) -> str:
    """The speed of one 2-core CPU and one GPU, from the benchmark records, and the GPU
    session's training figures."""
    cpu, gpu = _speed_cells(rec, "cpu"), _speed_cells(rec, "gpu")
    machines = []
    for where in ("cpu", "gpu"):
        m = (rec.read(f"{BENCH[where]}/all.json") or {}).get("machine", {})
        machines.append(
            f"{m.get('cpu_count', '?')}-core {m.get('cpu_model', '?')}, JAX {m.get('jax', '?')}"
        )
    lines = [
        f"| what | CPU only ({machines[0]}) | one NVIDIA H100 (host: {machines[1]}) |",
        "|---|---|---|",
    ]
    for i, what in enumerate(SPEED_ROWS):
        c = MISSING if cpu is None else cpu[i]
        g = MISSING if gpu is None else gpu[i]
        lines.append(f"| {what} | {c} | {g} |")
    lines += [
        "",
        "`python -m benchmarks.all --record`; records: `benchmarks/results/` (CPU) and "
        "`benchmarks/results/gpu-h100/` (GPU; benchmarks/README.md has the commands). Different "
        "machines, JAX versions and host CPUs: compare the columns as orders of magnitude. The "
        "MPC's solves run on the host CPU in both (OSQP), so on the GPU they take most of an "
        "iteration.",
    ]
    lines += render_gpu_session(rec)
    return "\n".join(lines)
