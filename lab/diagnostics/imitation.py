"""How well does a trained policy imitate the MPC, and how far does imitation alone get?

A diagnostic written for the behaviour-cloning extension (`pearl.bc_weight`, since removed:
docs/extensions.md, Removed options). The GP-MPC of the run (its own `mpc` settings, acting at
every step) drives closed-loop episodes on the first `train_tasks` training tasks and on the
`val` split of task seed `--select-seed`. On the MPC's own states of the validation episodes, and
of the training episodes (steps before a collision or the goal), it measures the squared action
error |a - a_mpc|^2 (summed over the two normalized action dimensions) of

* the run's deterministic policy tanh(mu(s, z)), with the prior z = 0 and with z inferred from
  the MPC episode itself as context;
* the mean MPC action (this error is the labels' variance: a policy above it imitates nothing);
* a supervised behaviour-cloning MLP (the policy's hidden sizes, no z, tanh output, Adam 1e-3,
  batches of 256) fitted to the (observation, MPC action) pairs of the training episodes, after
  each of `fit_steps` gradient steps.

The BC MLP at the step count with the lowest validation error is then run closed loop (no MPC)
on the `val` split of each of `--task-seeds` (method §8 metrics), the same 192 tasks on which
`python -m experiments.evaluate RUN --split val --task-seeds 1-8` scores the run's policy.

    python -m lab.diagnostics.imitation [--tiny | --full] [--out DIR] [--threads N] [--run
    DIR]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lab import harness

ROOT = Path(__file__).resolve().parents[2]  # the repository
DEFAULT_RUN = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2"
SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(train_tasks=2, val_tasks=2, fit_steps=(5, 10), task_seeds=(1,)),
    "default": dict(
        train_tasks=120, val_tasks=24, fit_steps=(250, 500, 1000, 3000), task_seeds=range(1, 9)
    ),
    "full": dict(
        train_tasks=120,
        val_tasks=24,
        fit_steps=(250, 500, 1000, 3000, 6000),
        task_seeds=range(1, 9),
    ),
}


def mpc_episodes(env, bridge, tasks, seed: int) -> dict:
    """GP-MPC closed loop on `tasks` through `bridge`; arrays [N, T(+1), ...] as numpy."""
    import jax
    import numpy as np

    from mpcpearl_jax.mpc import make_gp_mpc_rollout

    traj = jax.jit(make_gp_mpc_rollout(env, bridge))(jax.random.PRNGKey(seed), tasks)
    return jax.tree_util.tree_map(np.asarray, jax.block_until_ready(traj))


def observations(env, traj: dict, tasks):
    """The observation [N, T, O] of every visited state (pose at step t, time t)."""
    import jax
    import jax.numpy as jnp

    from mpcpearl_jax.envs.types import EnvState

    horizon = traj["action"].shape[1]
    pose = jnp.concatenate([traj["position"], traj["heading"][..., None]], -1)[:, :horizon]

    def per_task(poses, task):
        return jax.vmap(lambda p, t: env.observe(EnvState(pose=p, t=t), task))(
            poses.astype(jnp.float32), jnp.arange(horizon)
        )

    return jax.vmap(per_task)(pose, tasks)


def labelled(traj: dict) -> Any:
    """Mask [N, T] of the steps whose MPC action is a label: before a collision or the goal."""
    return ~traj["collision"] & ~traj["in_goal"]


def bc_mlp(hidden):
    import flax.linen as nn
    import jax.numpy as jnp

    class BC(nn.Module):
        @nn.compact
        def __call__(self, x):
            for h in hidden:
                x = nn.relu(nn.Dense(h)(x))
            return jnp.tanh(nn.Dense(2)(x))

    return BC()


def closed_loop(env, net):
    """`run(params, tasks) -> method §8 metrics` of the BC MLP driving alone; jitted once, so
    every task set of the same size reuses the compiled rollout."""
    import jax
    import jax.numpy as jnp

    from mpcpearl_jax.evaluation import metrics

    def episode(params, task):
        obs, state = env.reset(None, task)

        def body(carry, _):
            obs, state = carry
            obs, state, _, _, info = env.step(None, state, net.apply(params, obs), task)
            return (obs, state), (info.position, info.collision, info.in_goal)

        _, (pos, col, goal) = jax.lax.scan(body, (obs, state), None, env.config.horizon)
        return jnp.concatenate([state.pose[None, :2], pos]), col, goal

    rollout = jax.jit(jax.vmap(episode, in_axes=(None, 0)))

    def run(params, tasks) -> dict:
        pos, col, goal = rollout(params, tasks)
        return metrics.compute(pos, col, goal, tasks.goal, env.config.robot_radius)

    return run


def run_name(run: Path) -> str:
    """The run folder as recorded: repository-relative where it lies inside the repository."""
    return str(run.relative_to(ROOT) if run.is_relative_to(ROOT) else run)


def _split(errors: dict, which: str) -> dict[str, float]:
    return {"train_error": errors["train"][which], "val_error": errors["val"][which]}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument("--run", type=Path, default=DEFAULT_RUN, help="run directory (load_policy)")
    p.add_argument("--select-seed", type=int, default=0, help="task seed of the val MPC episodes")
    args = p.parse_args(argv)
    if args.select_seed < 0:  # a task-set seed; -1 was a NumPy ValueError after the first work
        p.error(f"--select-seed: a task-set seed is at least 0, got {args.select_seed}")
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = SIZES[size]

    import jax
    import jax.numpy as jnp
    import numpy as np
    import optax

    from mpcpearl_jax import metrics
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.mpc import MPCConfig, make_mpc_bridge

    pol = harness.load_runs("--run", [args.run])[0]
    cfg = pol.config
    env = make_env(cfg.env, **cfg.env_overrides)
    first = lambda tasks, n: jax.tree_util.tree_map(lambda a: a[:n], tasks)  # noqa: E731
    train_tasks = first(make_tasks(cfg.env, "train", cfg.task_seed), sz["train_tasks"])
    val_tasks = first(make_tasks(cfg.env, "val", args.select_seed), sz["val_tasks"])
    bridge = make_mpc_bridge(env, MPCConfig(**cfg.mpc.to_dict()))
    try:
        (tr, mpc_train_s), (va, mpc_val_s) = (
            harness.timed(lambda t=t: mpc_episodes(env, bridge, t, cfg.seed))
            for t in (train_tasks, val_tasks)
        )
    finally:
        bridge.close()
    x_tr, x_va = observations(env, tr, train_tasks), observations(env, va, val_tasks)
    m_tr, m_va = labelled(tr), labelled(va)
    xs_tr, ys_tr = jnp.asarray(np.asarray(x_tr)[m_tr]), jnp.asarray(tr["action"][m_tr])
    xs_va, ys_va = jnp.asarray(np.asarray(x_va)[m_va]), jnp.asarray(va["action"][m_va])
    sq = lambda a, b: float(jnp.mean(jnp.sum((a - b) ** 2, -1)))  # noqa: E731

    # the run's policy on the MPC's states
    def policy_error(x, traj, mask) -> dict[str, float]:
        labels = traj["action"][mask]
        z0 = jnp.zeros(x.shape[:-1] + (pol.latent_dim,))
        ctx = jnp.concatenate(
            [x[:, :-1], traj["action"][:, :-1], traj["reward"][:, :-1, None], x[:, 1:]], -1
        )
        z = jax.vmap(lambda c: pol.nets.sample_z(pol.params["encoder"], c, None, None))(ctx)
        z = jnp.broadcast_to(z[:, None], z0.shape)
        act = lambda z: np.asarray(pol.nets.act(pol.params["policy"], x, z, None))[mask]  # noqa: E731
        return {"prior_z": sq(act(z0), labels), "posterior_z": sq(act(z), labels)}

    policy_err = {"val": policy_error(x_va, va, m_va), "train": policy_error(x_tr, tr, m_tr)}
    label_var, train_var = sq(ys_va, jnp.mean(ys_va, 0)), sq(ys_tr, jnp.mean(ys_tr, 0))

    # supervised behaviour cloning on the training episodes
    net = bc_mlp(tuple(cfg.pearl.hidden))
    opt = optax.adam(1e-3)
    loss = lambda prm, x, y: jnp.mean(jnp.sum((net.apply(prm, x) - y) ** 2, -1))  # noqa: E731

    @jax.jit
    def step(prm, st, key):
        idx = jax.random.randint(key, (256,), 0, xs_tr.shape[0])
        upd, st = opt.update(jax.grad(loss)(prm, xs_tr[idx], ys_tr[idx]), st)
        return optax.apply_updates(prm, upd), st

    prm = net.init(jax.random.PRNGKey(cfg.seed), xs_tr[:1])
    st, key, done, curve, snapshots = opt.init(prm), jax.random.PRNGKey(cfg.seed + 1), 0, [], {}
    for n in sz["fit_steps"]:
        for _ in range(n - done):
            key, sub = jax.random.split(key)
            prm, st = step(prm, st, sub)
        done = n
        snapshots[n] = prm
        curve.append(
            {
                "steps": n,
                "train_error": loss(prm, xs_tr, ys_tr),
                "val_error": loss(prm, xs_va, ys_va),
            }
        )
    curve = [{k: v if k == "steps" else float(v) for k, v in row.items()} for row in curve]
    best = min(curve, key=lambda row: row["val_error"])["steps"]

    drive = closed_loop(env, net)
    per_seed = {
        int(ts): drive(snapshots[best], make_tasks(cfg.env, "val", int(ts)))
        for ts in sz["task_seeds"]
    }
    pooled = {k: float(np.mean([m[k] for m in per_seed.values()])) for k in ("SR", "CFR")}

    def mpc_sr(traj: dict, tasks) -> float:
        pos, col, goal = traj["position"], traj["collision"], traj["in_goal"]
        return metrics.compute(pos, col, goal, tasks.goal, env.config.robot_radius)["SR"]

    rows = [
        {
            "model": "mean MPC action (label variance)",
            "train_error": train_var,
            "val_error": label_var,
        },
        {"model": "run policy, prior z", **_split(policy_err, "prior_z")},
        {"model": "run policy, z from the MPC episode", **_split(policy_err, "posterior_z")},
        *(
            {
                "model": f"BC MLP, {r['steps']} steps",
                "train_error": r["train_error"],
                "val_error": r["val_error"],
            }
            for r in curve
        ),
    ]
    results = {
        "run": run_name(args.run),
        "label_variance": label_var,
        "train_label_variance": train_var,
        "policy_error": policy_err,
        "bc_curve": curve,
        "bc_selected_steps": best,
        "bc_closed_loop": {"per_task_seed": per_seed, "mean": pooled},
        "samples": {"train": int(xs_tr.shape[0]), "val": int(xs_va.shape[0])},
        "gp_mpc_sr": {"train": mpc_sr(tr, train_tasks), "val": mpc_sr(va, val_tasks)},
        "mpc_seconds": {"train": mpc_train_s, "val": mpc_val_s},
    }
    config = {
        "size": size,
        **{k: list(v) if isinstance(v, range | tuple) else v for k, v in sz.items()},
        "select_seed": args.select_seed,
        "threads": threads,
    }
    name = harness.record_name("imitation", size, select_seed=(args.select_seed, 0))
    # the record before the table: a failing or closed standard output loses none of the work
    harness.write_record(name, config, results, args.out)
    title = f"imitation error |a - a_mpc|^2 on the MPC's states ({size})"
    harness.print_table(rows, ["model", "train_error", "val_error"], title)
    print(
        f"BC MLP ({best} steps) alone on val task seeds {list(per_seed)}: SR {pooled['SR']:.2f} "
        f"CFR {pooled['CFR']:.2f}; GP-MPC SR on its episodes: train "
        f"{results['gp_mpc_sr']['train']:.2f}, val {results['gp_mpc_sr']['val']:.2f}",
        flush=True,
    )
    return results


if __name__ == "__main__":
    main()
