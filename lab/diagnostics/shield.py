"""What does the test-time safety shield add, and how much of it is the learned policy's?

A diagnostic for the shield extension (`mpcpearl_jax.mpc.shield`, docs/extensions.md). On the `val`
split of each of `--task-seeds` (the 192 tasks of task seeds 1-8 by default, the same on which
`python -m experiments.evaluate RUN --split val --task-seeds 1-8` scores a run), it evaluates

* every run of `--runs` by the meta-test protocol (two adaptation episodes, then the scored one;
  `mpcpearl_jax.evaluation.evaluate.make_evaluator`), without the shield and with each shield
  setting of
  the margin x lookahead grid;
* a goal-seeking controller with the same shield settings, the control that tells how much of a
  shielded score is the shield's: it steers the direction of motion straight at the goal (the
  slip angle beta of eq. (1) set to the bearing error, clipped to +-pi/2) at full speed, slowing
  to reach the goal in one step when it is closer than one step at full speed.

For every (controller, shield) pair it prints and saves SR, CFR, the share of episodes that run
out of time without a contact, and the share of steps whose action the shield replaced, pooled
over the task seeds with the standard error over tasks. Settings are chosen on this split; the
test split is for reporting (`experiments.evaluate RUN --shield ...`).

    python -m lab.diagnostics.shield [--tiny | --full] [--out DIR] [--threads N] [--runs
    DIR ...]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lab import harness

ROOT = Path(__file__).resolve().parents[2]  # the repository
DEFAULT_RUNS = [
    ROOT / "results" / "restaurant" / name for name in ("mpc-pearl-eps0.2", "mpc-sac", "pearl")
]
SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(task_seeds=(1,), tasks=2, margins=(0.05,), lookaheads=(1,)),
    "default": dict(task_seeds=range(1, 9), tasks=None, margins=(0.05, 0.1), lookaheads=(1, 2)),
    "full": dict(
        task_seeds=range(1, 9), tasks=None, margins=(0.0, 0.05, 0.1, 0.2), lookaheads=(1, 2, 4)
    ),
}


def goal_seeking_action(pose, goal, cfg):
    """Normalised action [2] that moves the robot straight at the goal (see module doc)."""
    import jax.numpy as jnp

    from mpcpearl_jax.envs.dynamics import DELTA_MAX, wrap_angle

    d = goal - pose[:2]
    dist = jnp.linalg.norm(d)
    beta = jnp.clip(wrap_angle(jnp.arctan2(d[1], d[0]) - pose[2]), -DELTA_MAX, DELTA_MAX)
    # beta = atan(tan(delta) / 2) (dynamics.slip_angle) -> delta = atan2(2 sin beta, cos beta)
    delta = jnp.arctan2(2.0 * jnp.sin(beta), jnp.cos(beta))
    v = jnp.minimum(cfg.v_max, dist / cfg.dt)
    return jnp.stack([2.0 * v / cfg.v_max - 1.0, delta / DELTA_MAX])


def goal_seeking_evaluator(env, shield):
    """jitted (tasks [N]) -> dict of [N, ...] arrays as `make_evaluator` returns for one seed."""
    import jax
    import jax.numpy as jnp

    from mpcpearl_jax.mpc.shield import shield_step

    cfg = env.config

    def one(task):
        obs0, state0 = env.reset(jax.random.PRNGKey(0), task)

        def body(state, _):
            a = goal_seeking_action(state.pose, task.goal, cfg)
            shielded = jnp.zeros((), bool)
            if shield is not None:
                a, shielded = shield_step(env, state, a, task, shield)
            _, nstate, _, _, info = env.step(jax.random.PRNGKey(0), state, a, task)
            return nstate, (info.position, info.collision, info.in_goal, shielded)

        _, (pos, col, goal, sh) = jax.lax.scan(body, state0, None, length=cfg.horizon)
        pos = jnp.concatenate([state0.pose[None, :2], pos], 0)
        return {"position": pos, "collision": col, "in_goal": goal, "shielded": sh}

    return jax.jit(jax.vmap(one))


def episode_outcomes(result: dict, tasks, robot_radius: float) -> dict[str, Any]:
    """Per-task success, collision-free, timeout (no contact, goal never reached), shield rate."""
    import numpy as np

    from mpcpearl_jax.evaluation import metrics

    m = metrics.episode_metrics(
        result["position"], result["collision"], result["in_goal"], tasks.goal, robot_radius
    )
    success, free = np.asarray(m.success), np.asarray(m.collision_free)
    reached = np.asarray(result["in_goal"]).any(-1)
    return {
        "success": success.astype(float),
        "collision_free": free.astype(float),
        "timeout": (free & ~reached).astype(float),
        "shield_rate": np.asarray(result["shielded"]).mean(-1),
    }


def pool(per_seed: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    import numpy as np

    out = {}
    for k in per_seed[0]:
        x = np.concatenate([p[k] for p in per_seed])
        out[k] = {"mean": float(x.mean()), "se": float(x.std(ddof=1) / np.sqrt(len(x)))}
    return out


def _relative(path: Path) -> str:
    """`path` relative to the repository when inside it (records carry no machine paths)."""
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return Path(path).name


def val_config(size: str, threads: Any, seeds: list[int], tasks: int | None, runs) -> dict:
    """The record's config of a diagnostic on the val split of task seeds `seeds` (the first
    `tasks` tasks of each, None: all) for the runs `runs`."""
    return {
        "size": size,
        "threads": threads,
        "split": "val",
        "task_seeds": seeds,
        "tasks_per_seed": tasks or "all",
        "runs": [_relative(r) for r in runs],
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument(
        "--runs", type=Path, nargs="*", default=DEFAULT_RUNS, help="run directories (load_policy)"
    )
    p.add_argument(
        "--env-from",
        type=Path,
        default=DEFAULT_RUNS[0],
        help="run whose environment options (sensing radius) the goal-seeking control gets",
    )
    args = p.parse_args(argv)
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = SIZES[size]

    import jax

    from mpcpearl_jax.cli.errors import error_line
    from mpcpearl_jax.config import ExperimentConfig
    from mpcpearl_jax.envs import make_env, tasks_for
    from mpcpearl_jax.errors import CheckpointError, ConfigError
    from mpcpearl_jax.evaluation import evaluate as eval_lib
    from mpcpearl_jax.evaluation.evaluate import EVAL_SEED  # the unshielded rows reproduce it
    from mpcpearl_jax.mpc.shield import ShieldConfig
    from mpcpearl_jax.runfolder import load_config

    policies = harness.load_runs("--runs", args.runs)
    try:
        env_from = load_config(args.env_from)
    except (CheckpointError, ConfigError, OSError, ValueError) as e:
        harness.fail(f"--env-from: {error_line(e)}")
    env_names = {pol.config.env for pol in policies} | {env_from.env}
    if env_names != {"restaurant"}:
        raise SystemExit(f"error: --runs must be restaurant runs, got {sorted(env_names)}")
    shields = [None] + [
        ShieldConfig(margin=m, lookahead=k) for k in sz["lookaheads"] for m in sz["margins"]
    ]
    seeds = list(sz["task_seeds"])

    def val_tasks(env, pol_cfg, seed):  # the restaurant's val split of a task-set seed
        tasks = tasks_for(pol_cfg or ExperimentConfig(), "val", config=env.config, seed=seed)
        if sz["tasks"] is not None:
            tasks = jax.tree_util.tree_map(lambda a: a[: sz["tasks"]], tasks)
        return tasks

    rows, record_rows = [], []

    def add(name: str, shield, per_seed: list[dict[str, Any]], wall: float) -> None:
        pooled = pool(per_seed)
        label = (
            "none" if shield is None else f"margin {shield.margin:g}, lookahead {shield.lookahead}"
        )
        rows.append(
            {
                "controller": name,
                "shield": label,
                "SR": f"{pooled['success']['mean']:.2f} +- {pooled['success']['se']:.2f}",
                "CFR": f"{pooled['collision_free']['mean']:.2f}",
                "timeout": f"{pooled['timeout']['mean']:.2f}",
                "shielded steps": f"{pooled['shield_rate']['mean']:.3f}",
            }
        )
        record_rows.append(
            {
                "controller": name,
                "shield": None if shield is None else shield.__dict__,
                "pooled": pooled,
                "SR_per_task_seed": [float(p["success"].mean()) for p in per_seed],
                "wall_s": wall,
            }
        )

    # the goal-seeking control, in the environment of --env-from (its sensing radius bounds what
    # the shield sees)
    env0 = make_env("restaurant", **dict(env_from.env_overrides))
    task_sets = {s: val_tasks(env0, None, s) for s in seeds}
    for shield in shields:
        fn = goal_seeking_evaluator(env0, shield)
        per_seed, wall = [], 0.0
        for tasks in task_sets.values():
            res, dt = harness.timed(lambda f=fn, t=tasks: jax.device_get(f(t)))
            wall += dt
            per_seed.append(episode_outcomes(res, tasks, env0.config.robot_radius))
        add("goal-seeking", shield, per_seed, wall)

    for run, pol in zip(args.runs, policies, strict=True):
        cfg = pol.config
        env = make_env(cfg.env, **cfg.env_overrides)
        params = jax.tree_util.tree_map(lambda x: x[None], pol.params)
        task_sets = {s: val_tasks(env, cfg, s) for s in seeds}
        for shield in shields:
            fn = eval_lib.make_evaluator(
                env,
                pol.nets,
                cfg.train.eval_adapt_episodes,
                t_update=cfg.train.t_update,
                shield=shield,
            )
            per_seed, wall = [], 0.0
            for tasks in task_sets.values():
                res, dt = harness.timed(
                    lambda f=fn, p=params, t=tasks: jax.device_get(
                        f(jax.random.PRNGKey(EVAL_SEED), p, t)
                    )
                )
                wall += dt
                res = jax.tree_util.tree_map(lambda x: x[0], res)
                per_seed.append(episode_outcomes(res, tasks, env.config.robot_radius))
            add(run.name, shield, per_seed, wall)

    first = "" if sz["tasks"] is None else f" (first {sz['tasks']} tasks each)"
    title = f"shield on restaurant/val, task seeds {seeds[0]}-{seeds[-1]}{first}"
    cols = ["controller", "shield", "SR", "CFR", "timeout", "shielded steps"]
    config = {
        **val_config(size, threads, seeds, sz["tasks"], args.runs),
        "env_from": _relative(args.env_from),
        "margins": list(sz["margins"]),
        "lookaheads": list(sz["lookaheads"]),
        "goal_seeking": "direction of motion at the goal, full speed (lab.diagnostics.shield doc)",
    }
    name = harness.record_name("shield", size)  # --runs are the record's config
    return harness.report(name, title, rows, cols, config, record_rows, args.out)


if __name__ == "__main__":
    main()
