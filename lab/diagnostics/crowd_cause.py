"""Why does a late crowd cost the policies? Interventions on what the policy sees.

A diagnostic for the robustness table (docs/research-log.md, docs/method.md §8a). On the `val`
split of each of `--task-seeds` (the 192 tasks of task seeds 1-8 by default, those of
`python -m experiments.evaluate RUN --split val --task-seeds 1-8 --perturb delay=K`), every run
of `--runs` is scored by the meta-test protocol (two adaptation episodes, then the scored one;
`mpcpearl_jax.evaluation.evaluate.make_evaluator`) with the crowd delayed by 0 and by `--delay`
steps
(`envs.perturb`), under these conditions:

* `as trained`: the observation the policy was trained with (reproduces experiments.evaluate).
* `clock follows the crowd` (runs with `env.observe_time`): the observation's clock reads
  max(t - K, 0), the step of the crowd's own timetable, so a policy that times its moves by the
  clock sees the timetable it learned; the people it sees are unchanged. If this restores the
  unperturbed score, the clock is how the policy anticipates the crowd.
* `blind`: no person is ever in the observation (every presence flag off); the people still
  collide. The score a policy keeps without seeing anyone is what it does from memory.
* `zero-shot`: no adaptation episode (z from the prior): the value of the context.

Beside SR / CFR it reports how far the robot's path moves when the crowd is late: the largest
distance over the first `--delay` steps between its positions with the delayed and the
unperturbed crowd, averaged over tasks (0 = the robot drives the same path whether or not people
still stand at their start), and the share of episodes with a contact in those steps.

    python -m lab.diagnostics.crowd_cause [--tiny] [--delay 12] [--runs DIR ...] [--out DIR]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lab import harness
from lab.diagnostics.shield import _relative, episode_outcomes, pool, val_config

ROOT = Path(__file__).resolve().parents[2]  # the repository
DEFAULT_RUNS = [
    ROOT / "results" / "restaurant" / name for name in ("mpc-pearl-eps0.2", "pearl", "mpc-sac")
]
SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(task_seeds=(1,), tasks=2),
    "default": dict(task_seeds=range(1, 9), tasks=None),
    "full": dict(task_seeds=range(1, 9), tasks=None),
}


def intervened_env(config, clock_lag: int = 0, blind: bool = False):
    """A `NavEnv` whose observation is intervened on (diagnostic only; dynamics, reward,
    collisions unchanged): the clock reads max(t - clock_lag, 0), and with `blind` no person is
    present in the observation."""
    import jax.numpy as jnp

    from mpcpearl_jax.envs import observation
    from mpcpearl_jax.envs.navigation import NavEnv

    class Intervened(NavEnv):
        def observe(self, state, params):
            humans, mask = self.humans_at(params, state.t)
            prev, prev_mask = self.humans_at(params, jnp.maximum(state.t - 1, 0))
            if blind:
                mask, prev_mask = jnp.zeros_like(mask), jnp.zeros_like(prev_mask)
            t = jnp.maximum(state.t - clock_lag, 0)
            lo, hi = params.static_lo, params.static_hi
            return observation.observation(
                self.config, state.pose, t, humans, mask, prev, prev_mask, lo, hi, params.goal
            )

    return Intervened(config)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument(
        "--runs", type=Path, nargs="*", default=DEFAULT_RUNS, help="run directories (load_policy)"
    )
    p.add_argument("--delay", type=int, default=12, help="the crowd's delay in steps (K)")
    args = p.parse_args(argv)
    from mpcpearl_jax.envs.perturb import MAX_DELAY

    if not 1 <= args.delay <= MAX_DELAY:
        harness.fail(f"--delay {args.delay}: must be in [1, {MAX_DELAY}] steps")
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = SIZES[size]

    import jax
    import numpy as np

    from mpcpearl_jax.envs import make_env, tasks_for
    from mpcpearl_jax.envs.perturb import Perturbation, perturb_tasks
    from mpcpearl_jax.evaluation import evaluate as eval_lib
    from mpcpearl_jax.evaluation.evaluate import EVAL_SEED

    policies = harness.load_runs("--runs", args.runs)
    pairs = zip(args.runs, policies, strict=True)
    others = [str(r) for r, pol in pairs if pol.config.env != "restaurant"]
    if others:
        harness.fail(f"--runs: must be restaurant runs, not {', '.join(others)}")
    seeds = list(sz["task_seeds"])
    k = args.delay
    rows, record_rows = [], []

    for run, pol in zip(args.runs, policies, strict=True):
        cfg = pol.config
        env = make_env(cfg.env, **cfg.env_overrides)
        params = jax.tree_util.tree_map(lambda x: x[None], pol.params)
        base = {}
        for s in seeds:
            t = tasks_for(cfg, "val", config=env.config, seed=s)
            if sz["tasks"] is not None:
                t = jax.tree_util.tree_map(lambda a, n=sz["tasks"]: a[:n], t)
            base[s] = t
        conditions = [
            ("as trained", 0, dict(), None),
            ("blind", 0, dict(blind=True), None),
            ("zero-shot", 0, dict(), 0),
            ("as trained", k, dict(), None),
            ("blind", k, dict(blind=True), None),
            ("zero-shot", k, dict(), 0),
        ]
        if env.config.observe_time:
            conditions.insert(4, ("clock follows the crowd", k, dict(clock_lag=k), None))
        paths0: dict[tuple[str, int], Any] = {}
        for name, delay, intervention, episodes in conditions:
            ep = cfg.train.eval_adapt_episodes if episodes is None else episodes
            fn = eval_lib.make_evaluator(
                intervened_env(env.config, **intervention),
                pol.nets,
                ep,
                t_update=cfg.train.t_update,
            )
            per_seed, wall, shift, early = [], 0.0, [], []
            for s, tasks in base.items():
                tasks = perturb_tasks(tasks, Perturbation(delay=delay))
                key = jax.random.PRNGKey(EVAL_SEED)
                res, dt = harness.timed(
                    lambda f=fn, p=params, t=tasks, k=key: jax.device_get(f(k, p, t))
                )
                wall += dt
                res = jax.tree_util.tree_map(lambda x: x[0], res)
                out = episode_outcomes(res, tasks, env.config.robot_radius)
                out.pop("shield_rate")
                per_seed.append(out)
                pos = np.asarray(res["position"])  # [N, T + 1, 2]
                early.append(np.asarray(res["collision"])[:, :k].any(-1).astype(float))
                if delay == 0:
                    paths0[(name, s)] = pos
                else:
                    ref = paths0.get((name, s), paths0[("as trained", s)])
                    d = np.linalg.norm(pos[:, : k + 1] - ref[:, : k + 1], axis=-1)
                    shift.append(d.max(-1))
            pooled = pool(per_seed)
            early_rate = float(np.concatenate(early).mean())
            path_shift = float(np.concatenate(shift).mean()) if shift else None
            rows.append(
                {
                    "run": run.name,
                    "crowd": f"delay {delay}" if delay else "as drawn",
                    "observation": name,
                    "SR": f"{pooled['success']['mean']:.2f} +- {pooled['success']['se']:.2f}",
                    "CFR": f"{pooled['collision_free']['mean']:.2f}",
                    f"contact in steps 1-{k}": f"{early_rate:.2f}",
                    "path shift (m)": "" if path_shift is None else f"{path_shift:.2f}",
                }
            )
            record_rows.append(
                {
                    "run": _relative(run),
                    "delay": delay,
                    "condition": name,
                    "adaptation_episodes": ep,
                    "pooled": pooled,
                    "SR_per_task_seed": [float(x["success"].mean()) for x in per_seed],
                    "early_contact_rate": early_rate,
                    "path_shift_m": path_shift,
                    "wall_s": wall,
                }
            )

    first = "" if sz["tasks"] is None else f" (first {sz['tasks']} tasks each)"
    title = f"crowd delay {k} on restaurant/val, task seeds {seeds[0]}-{seeds[-1]}{first}"
    cols = [
        "run",
        "crowd",
        "observation",
        "SR",
        "CFR",
        f"contact in steps 1-{k}",
        "path shift (m)",
    ]
    config = {**val_config(size, threads, seeds, sz["tasks"], args.runs), "delay": k}
    name = harness.record_name(  # --full is the default size
        "crowd_cause",
        "tiny" if size == "tiny" else "default",
        delay=(k, 12),
    )
    return harness.report(name, title, rows, cols, config, record_rows, args.out)


if __name__ == "__main__":
    main()
