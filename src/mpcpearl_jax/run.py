"""Run an experiment: train with checkpoints and a metrics log, evaluate, write figures and the
results table. Used by `python -m experiments.restaurant` and `python -m experiments.sidewalk`.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mpcpearl_jax.checkpoint import (
    Checkpointer,
    CheckpointError,
    check_resumable,
    load_config,
    save_config,
)
from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.metrics import METRIC_NAMES
from mpcpearl_jax.trainer import Trainer, TrainState

LOG_FILE = "metrics.jsonl"

# method §8: the paper's numbers (restaurant: 24 unseen tasks after two adaptation episodes).
PAPER = {
    "restaurant": {
        "PEARL": {"SR": 0.36, "TT": 64.32, "CFR": 0.99, "SPL": 0.31, "MGD": 33.59},
        "GP-MPC": {"SR": 0.67, "TT": 59.62, "CFR": 0.83, "SPL": 0.63, "MGD": 30.13},
        "MPC-SAC": {"SR": 0.17, "TT": 73.33, "CFR": 0.69, "SPL": 0.14, "MGD": 74.90},
        "MPC-PEARL 0.2": {"SR": 0.92, "TT": 38.61, "CFR": 0.99, "SPL": 0.78, "MGD": 22.16},
        "MPC-PEARL 0.2 (online)": {"SR": 0.83, "TT": 51.65, "CFR": 0.90, "SPL": 0.65, "MGD": 45.79},
    },
    "sidewalk": {
        "MPC-PEARL 0.2 (online)": {"SR": 0.67, "TT": 211.35, "SPL": 0.44},
        "GP-MPC": {"SR": 0.48},
        "PEARL (online)": {"SR": 0.03, "TT": 249.61, "CFR": 0.84, "SPL": 0.03},
    },
}


def _read_log(path: Path, upto: int) -> list[dict]:
    if not path.is_file():
        return []
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in rows if r.get("iteration", 0) <= upto]


def _write_log(path: Path, rows: list[dict]) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def _eval_row(trainer: Trainer, state: TrainState) -> dict[str, Any]:
    online = trainer.cfg.online_eval
    ev = trainer.evaluate(state, online=online)
    ev.pop("_raw")
    return {f"test_{k}": v for k, v in ev.items() if not k.endswith("_per_seed")}


def train(
    cfg: ExperimentConfig, out: str | Path, resume: bool = False, progress: bool = True
) -> tuple[Trainer, TrainState]:
    """Train `cfg` into `out` (checkpoints, config.json, metrics.jsonl); -> (trainer, state)."""
    run_dir = Path(out)
    if resume:
        saved = load_config(run_dir)
        check_resumable(saved, cfg, run_dir)
    elif (run_dir / "checkpoints").exists() and any((run_dir / "checkpoints").iterdir()):
        raise CheckpointError(
            f"{run_dir} already holds checkpoints: pass --resume to continue "
            "or choose another --out"
        )
    save_config(run_dir, cfg)
    trainer = Trainer(cfg)
    ckpt = Checkpointer(run_dir, keep=cfg.train.keep_checkpoints)
    state = trainer.init_state()
    log_path = run_dir / LOG_FILE
    if resume and ckpt.latest() is not None:
        state = ckpt.restore(state)
    done = int(np.asarray(state.iteration)[0])
    rows = _read_log(log_path, done)
    _write_log(log_path, rows)
    total = cfg.train.iterations
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            total=total, initial=done, desc=f"{cfg.env} eps={cfg.train.eps}", dynamic_ncols=True
        )
    t_start = time.perf_counter()
    while done < total:
        state, log = trainer.iteration(state)
        done = log["iteration"]
        tc = cfg.train
        if (tc.eval_interval and done % tc.eval_interval == 0) or done == total:
            t0 = time.perf_counter()
            log.update(_eval_row(trainer, state))
            log["eval_s"] = time.perf_counter() - t0
        log["wall_s"] = time.perf_counter() - t_start
        rows.append(log)
        with log_path.open("a") as f:
            f.write(json.dumps(log) + "\n")
        if done % tc.checkpoint_interval == 0 or done == total:
            ckpt.save(done, state, _policy_params(state))
        if bar is not None:
            post = {"ret": f"{log['train_return']:.0f}", "mpc": f"{log['train_mpc_share']:.2f}"}
            if "test_SR" in log:
                post.update(SR=f"{log['test_SR']:.2f}", CFR=f"{log['test_CFR']:.2f}")
            bar.set_postfix(post)
            bar.update(1)
    if bar is not None:
        bar.close()
    ckpt.close()
    return trainer, state


def _policy_params(state: TrainState) -> dict:
    p = state.learner.params
    return jax.device_get({"policy": p["policy"], "encoder": p["encoder"]})


def final_evaluation(
    trainer: Trainer, state: TrainState, out: str | Path, label: str
) -> dict[str, Any]:
    """Evaluate on test (adaptation and online) and OOD tasks; save results.json + figures."""
    from mpcpearl_jax.envs import make_tasks

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
    try:
        kw = {"data": trainer.cfg.data} if trainer.cfg.data else {}
        ood = make_tasks(
            trainer.cfg.env, "ood", trainer.cfg.task_seed, config=trainer.env.config, **kw
        )
        res = trainer.evaluate(state, tasks=ood)
        res.pop("_raw")
        results["ood_adapt"] = res
    except ValueError as e:  # a family without an OOD split
        results["ood_adapt"] = {"skipped": str(e)}
    results["paper"] = PAPER.get(trainer.cfg.env, {})
    (run_dir / "results.json").write_text(json.dumps(results, indent=2))
    print(results_table(results))
    plot_learning_curves(run_dir)
    _trajectory_figure(trainer, raw, run_dir)
    return results


def results_table(results: dict[str, Any]) -> str:
    """Markdown table: this run (adaptation / online / OOD) next to the paper's columns."""
    cols = [
        (f"{results['label']}", results["test_adapt"]),
        (f"{results['label']} (online)", results["test_online"]),
    ]
    if "SR" in results.get("ood_adapt", {}):
        cols.append((f"{results['label']} (OOD)", results["ood_adapt"]))
    cols += [(f"paper {k}", v) for k, v in results.get("paper", {}).items()]
    lines = ["| metric | " + " | ".join(c for c, _ in cols) + " |", "|---|" + "---|" * len(cols)]
    for m in METRIC_NAMES:
        vals = []
        for _, d in cols:
            v = d.get(m)
            vals.append("-" if v is None else f"{v:.2f}")
        lines.append(f"| {m} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def plot_learning_curves(run_dir: Path) -> Path | None:
    """learning_curves.png: train return, test return, SR, CFR against iteration."""
    rows = _read_log(run_dir / LOG_FILE, 10**9)
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.5))
    it = [r["iteration"] for r in rows]
    axes[0].plot(it, [r["train_return"] for r in rows], lw=1)
    axes[0].set_title("train return (posterior episodes)")
    ev = [r for r in rows if "test_SR" in r]
    for ax, key, title in zip(
        axes[1:],
        ("test_return", "test_SR", "test_CFR"),
        ("test return", "test SR", "test CFR"),
        strict=True,
    ):
        ax.plot([r["iteration"] for r in ev], [r[key] for r in ev], marker="o", ms=3)
        ax.set_title(title)
    for ax in axes:
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = run_dir / "learning_curves.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _trajectory_figure(trainer: Trainer, raw: dict, run_dir: Path, n: int = 4) -> None:
    """The first n test tasks with seed 0's evaluated episode (paper-style figures)."""
    from mpcpearl_jax import viz

    for i in range(min(n, int(trainer.test_tasks.start.shape[0]))):
        task = jax.tree_util.tree_map(lambda x, i=i: x[i], trainer.test_tasks)
        pos = np.asarray(raw["position"][0, i])
        col = np.asarray(raw["collision"][0, i])
        path = run_dir / f"trajectory_test{i}.png"
        if trainer.cfg.env == "sidewalk":  # the paper's sidewalk style: pedestrians as circles
            from mpcpearl_jax.envs.sidewalk import plot_sidewalk

            plot_sidewalk(task, trainer.env.config, {"policy (seed 0)": (pos, col)}, path)
        else:
            viz.save_trajectory_figure(
                path, task, {"policy (seed 0)": pos}, {"policy (seed 0)": col}, trainer.env.config
            )
