"""Seconds per PEARL gradient step: this project (JAX) vs. a straightforward PyTorch baseline.

Both sides run the same update (method §7: V + target V, twin Q, tanh-Gaussian policy, context
encoder with KL, Adam) on the same random batches of the same shapes, on the same CPU cores: the
process is pinned to `--threads` cores, PyTorch gets `set_num_threads(threads)` and XLA sizes its
pool from the pinned cores (both recorded). JAX and PyTorch samples are interleaved (round r
times JAX, then PyTorch) so that load from other processes hits both alike; the ratio is taken
from the medians and, per round, from the paired samples. Replay-buffer sampling is not timed on
either side.

Also: aggregate gradient steps/s when several seeds are trained in one program (the learner
state gets a leading seed axis and the update is `vmap`ped over it, each seed with its own batch).

    python -m benchmarks.pearl_step [--tiny | --full] [--out DIR] [--threads N]
"""

from __future__ import annotations

import statistics
import time
from typing import Any

from benchmarks import harness

# The authors' PyTorch code on a 2-core CPU like this one (method §9), for context only.
AUTHORS_CPU_ANCHOR_S = {"threads_2": 0.259, "threads_1": 0.459}
SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(paper=False, steps_per_sample=2, rounds=2, seeds=(2,)),
    "default": dict(paper=True, steps_per_sample=5, rounds=5, seeds=(1, 2, 4)),
    "full": dict(paper=True, steps_per_sample=10, rounds=10, seeds=(1, 2, 4, 8)),
}
OBS_DIM, ACTION_DIM = 25, 2  # the restaurant env


def pearl_config(paper: bool):
    from mpcpearl_jax.pearl import PearlConfig

    if paper:
        return PearlConfig()  # method §7 sizes
    return PearlConfig(
        hidden=(32, 32), encoder_hidden=(32, 32), meta_batch=2, batch_size=16, context_size=8
    )


def random_numpy_batch(cfg, seed: int, lead: tuple[int, ...] = ()) -> dict[str, Any]:
    """Random transitions [*lead, MB, B, ...] and context [*lead, MB, C, 2 O + A + 1]."""
    import numpy as np

    rng = np.random.default_rng(seed)
    mb, b, c = cfg.meta_batch, cfg.batch_size, cfg.context_size
    u = lambda *s: rng.uniform(-1, 1, (*lead, *s)).astype(np.float32)
    return {
        "obs": u(mb, b, OBS_DIM),
        "action": u(mb, b, ACTION_DIM),
        "reward": u(mb, b),
        "next_obs": u(mb, b, OBS_DIM),
        "done": (rng.uniform(size=(*lead, mb, b)) < 0.0125).astype(np.float32),
        "context": u(mb, c, 2 * OBS_DIM + ACTION_DIM + 1),
    }


# ------------------------------------------------------------------------------- JAX
class JaxSide:
    """The project's jitted update, compiled ahead of time, stepping `seeds` learners at once."""

    def __init__(self, cfg, seeds: int | None):
        import jax
        import jax.numpy as jnp

        from mpcpearl_jax.pearl import Networks, Transitions, init_learner, make_update

        self.jax = jax
        nets = Networks(cfg, OBS_DIM, ACTION_DIM)
        update = make_update(nets)
        init = lambda k: init_learner(k, nets)
        lead = () if seeds is None else (seeds,)
        nb = random_numpy_batch(cfg, seed=0, lead=lead)
        self.batch = Transitions(
            **{k: jnp.asarray(v) for k, v in nb.items() if k in Transitions._fields}
        )
        self.context = jnp.asarray(nb["context"])
        key = jax.random.key(0)
        if seeds is None:
            self.state, fn = init(key), update
        else:
            self.state = jax.vmap(init)(jax.random.split(key, seeds))
            fn = jax.jit(jax.vmap(update))
        self.keys = list(jax.random.split(jax.random.key(1), 64))
        if seeds is not None:
            self.keys = [jax.random.split(k, seeds) for k in self.keys]
        lowered = fn.lower(self.state, self.batch, self.context, self.keys[0])
        self.update, self.compile_s = harness.timed(lowered.compile)
        self.i = 0

    def steps(self, n: int) -> None:
        for _ in range(n):
            self.state, self.metrics = self.update(
                self.state, self.batch, self.context, self.keys[self.i % len(self.keys)]
            )
            self.i += 1
        self.jax.block_until_ready(self.state)


class TorchSide:
    """The PyTorch baseline on the same batch."""

    def __init__(self, cfg, device: str = "cpu"):
        import torch

        from benchmarks.torch_pearl import TorchPearl, TorchPearlSizes

        self.model = TorchPearl(OBS_DIM, ACTION_DIM, TorchPearlSizes.like(cfg), device=device)
        nb = random_numpy_batch(cfg, seed=0)
        names = ("obs", "action", "reward", "next_obs", "done", "context")
        self.batch = [torch.from_numpy(nb[k]).to(device) for k in names]

    def steps(self, n: int) -> None:
        for _ in range(n):
            self.losses = self.model.step(*self.batch)


# ---------------------------------------------------------------------------- timing
def interleaved(sides: dict[str, Any], steps: int, rounds: int) -> dict[str, Any]:
    """Seconds per step of each side, sampled in alternation; one warm-up sample each."""
    for s in sides.values():
        s.steps(1)
    raw: dict[str, list[float]] = {k: [] for k in sides}
    for _ in range(rounds):
        for name, side in sides.items():
            t0 = time.perf_counter()
            side.steps(steps)
            raw[name].append((time.perf_counter() - t0) / steps)
    return {k: harness.summarize(v) for k, v in raw.items()}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = harness.common_parser(__doc__.split("\n\n")[0])
    parser.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=None,
        help="numbers of seeds stepped in one program (default: the size's, e.g. 1 2 4)",
    )
    args = parser.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = dict(SIZES[size])
    if args.seeds:
        if min(args.seeds) < 1:
            raise SystemExit("--seeds: every number of seeds must be at least 1")
        sz["seeds"] = tuple(args.seeds)
    torch_info = harness.torch_threads(threads["threads"])
    if torch_info is None:
        print(harness.TORCH_MISSING, flush=True)
    cfg = pearl_config(sz["paper"])

    sides: dict[str, Any] = {"jax": JaxSide(cfg, None)}
    compile_s = {"jax": sides["jax"].compile_s}
    torch_device = None
    if torch_info is not None:
        torch_device = harness.torch_device()
        sides["torch"] = TorchSide(cfg, torch_device)
    step_t = interleaved(sides, sz["steps_per_sample"], sz["rounds"])

    rows = [
        {
            "impl": k,
            "s_per_step": v["median_s"],
            "p25": v["p25_s"],
            "p75": v["p75_s"],
            "steps_per_s": 1.0 / v["median_s"],
        }
        for k, v in step_t.items()
    ]
    ratio: dict[str, Any] = {}
    if "torch" in step_t:
        paired = [
            t / j for t, j in zip(step_t["torch"]["raw_s"], step_t["jax"]["raw_s"], strict=True)
        ]
        ratio = {
            "torch_over_jax_median": step_t["torch"]["median_s"] / step_t["jax"]["median_s"],
            "torch_over_jax_paired_median": statistics.median(paired),
            "paired_raw": paired,
            "target_jax_1.5x_faster": step_t["torch"]["median_s"] / step_t["jax"]["median_s"]
            >= 1.5,
        }
        rows[1]["x_faster_than_torch"] = 1.0
        rows[0]["x_faster_than_torch"] = ratio["torch_over_jax_median"]
    cols = ["impl", "s_per_step", "p25", "p75", "steps_per_s", "x_faster_than_torch"]
    harness.print_table(rows, cols, f"PEARL gradient step ({size}, {threads['threads']} threads)")
    if ratio:
        print(
            f"JAX is {ratio['torch_over_jax_median']:.2f}x faster than the PyTorch baseline "
            f"(paired per-round median {ratio['torch_over_jax_paired_median']:.2f}x)",
            flush=True,
        )
    del sides

    seed_rows = []
    for n in sz["seeds"]:
        side = JaxSide(cfg, n)
        t = interleaved(
            {"jax": side}, max(1, sz["steps_per_sample"] // 2), max(2, sz["rounds"] // 2)
        )
        med = t["jax"]["median_s"]
        seed_rows.append(
            {
                "seeds": n,
                "s_per_step_all_seeds": med,
                "compile_s": side.compile_s,
                "agg_steps_per_s": n / med,
                "timing": t["jax"],
            }
        )
    base = 1.0 / step_t["jax"]["median_s"]
    for r in seed_rows:
        r["vs_one_seed_unvmapped"] = r["agg_steps_per_s"] / base
    harness.print_table(
        seed_rows,
        ["seeds", "s_per_step_all_seeds", "agg_steps_per_s", "vs_one_seed_unvmapped", "compile_s"],
        "Several seeds in one program (vmap over a seed axis)",
    )
    results = {
        "step": step_t,
        "compile_s": compile_s,
        "ratio": ratio,
        "seeds": seed_rows,
        "authors_cpu_anchor_s_per_step (method §9, not measured here)": AUTHORS_CPU_ANCHOR_S,
    }
    config = {
        "size": size,
        **sz,
        "pearl": _asdict(cfg),
        "obs_dim": OBS_DIM,
        "action_dim": ACTION_DIM,
        "threads": threads,
        "torch": torch_info,
        "torch_device": torch_device,
        "data": "fixed random batch per side (no replay sampling timed)",
    }
    harness.write_record("pearl_step", config, results, args.out)
    return results


def _asdict(cfg) -> dict[str, Any]:
    import dataclasses

    return dataclasses.asdict(cfg)


if __name__ == "__main__":
    main()
