"""Can a policy learn the MPC by imitation on its own states (DAgger), and with which inputs?

A diagnostic beside `lab.diagnostics.imitation`, which found that cloning the MPC's own
episodes does
not transfer (the clone leaves the MPC's states and collides). Here the clone is trained by
DAgger (Ross et al., 2011): in round r every training task (its table layout, with a crowd
behaviour re-drawn for the round, as `train.redraw_behaviours` does) is driven by a mixture that
executes the MPC's action with probability beta_r = 0.5^r (1 in round 0) and otherwise the
clone's action plus Gaussian noise (std 0.1); the MPC (the run's `mpc` settings) is solved on
every step either way, and each step before the first collision or the goal whose solve was safe
adds (observation, MPC action) to the data set. After each round the clone (an MLP of
`--hidden` sizes, tanh output, Adam 1e-3, batches of 256) takes `fit_steps` more gradient steps
on all data so far, and drives alone (no MPC) on the `val` split of task seeds 1-2 (48 tasks);
after the last round on the `val` split of task seeds 1-8 (192 tasks, as `experiments.evaluate
RUN --split val --task-seeds 1-8` for a trained run).

The observation is the run's (its `env` overrides), plus the egocentric entries with
`--relative` (`env.observe_relative`) and people listed nearest first with `--sorted`
(`env.observe_sorted`): the comparison of inputs under the same data-collection scheme. The
representation is the clone's: `--encoder mlp` (one MLP over the flat observation, as the
policy of `pearl.crowd_encoder` "none") or `--encoder attention` (the policy's crowd encoder,
`pearl.networks.CrowdEncoder`, in front of the same MLP; it adds `env.observe_relative` and
`env.observe_presence`; `--presence` adds the presence entries to the MLP's observation), with
`--forecast K` the people's constant-velocity positions K points
ahead (`env.observe_forecast`, every `--stride` steps). `--labels N` drives N times as many
tasks per round (each training layout with N crowds drawn for the round), so N times the labels
at the same number of rounds; `--seed` moves the DAgger mixture, the noise, the minibatches and
the clone's initialisation (the tasks and crowds stay the same, so arms are paired).

    python -m lab.diagnostics.dagger [--tiny] [--relative] [--sorted] [--encoder mlp|attention]
    [--presence] [--forecast K] [--stride S] [--labels N] [--seed S] [--rounds N] [--out DIR]

The record (with the clone's parameter count),
DIR/dagger[-relative][-sorted][-ENCODER|-presence][-forecastKxS][-labelsN][-tiny][-roundsN]
[-hiddenAxB][-runNAME][-seedS].json, names every setting that is not the default, so runs of
another size or setting never replace each other's records.

`--report DIR` (alone) reads the records in DIR, groups them by arm (everything but the seed)
and writes DIR/README.md and DIR/report.json (records of the tiny size are left out, and
named as such): per arm the final SR of each seed on the 192
validation tasks, mean +- standard error over seeds, the worst seed, IQM with its bootstrap
interval and the probability that a seed of the arm beats a seed of the MLP arm of the same
inputs and label scale (rliable, as `lab.screen` computes them).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lab import harness
from lab.diagnostics.crowd_cause import intervened_env
from lab.diagnostics.imitation import DEFAULT_RUN, bc_mlp, closed_loop, run_name

SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(train_tasks=2, rounds=2, fit_steps=5, round_seeds=(1,), final_seeds=(1,)),
    "default": dict(
        train_tasks=120, rounds=12, fit_steps=2000, round_seeds=(1, 2), final_seeds=range(1, 9)
    ),
}
SIZES["full"] = SIZES["default"]
NOISE = 0.1  # std of the Gaussian noise on the clone's executed actions
BATCH = 256


def bc_attention(hidden, crowd):
    """The clone with the policy's crowd encoder (`CrowdSpec` `crowd`) in front of an MLP of
    `hidden` sizes, tanh output."""
    import flax.linen as nn
    import jax.numpy as jnp

    from mpcpearl_jax.pearl.networks import CrowdEncoder

    class BC(nn.Module):
        @nn.compact
        def __call__(self, x):
            x = CrowdEncoder(crowd, name="crowd")(x)
            for h in hidden:
                x = nn.relu(nn.Dense(h)(x))
            return jnp.tanh(nn.Dense(2)(x))

    return BC()


def record_name(args) -> str:
    """The record's file stem: the inputs, the encoder, the label scale and the seed."""
    name = "dagger" + ("-relative" if args.relative else "") + ("-sorted" if args.sorted else "")
    if args.encoder != "mlp":
        name += f"-{args.encoder}"
        if (args.encoder, args.dim) != ("attention", 64):
            name += f"{args.dim}"
        if args.static != "pool":
            name += f"-tables{args.static}"
        if args.layers != 2:
            name += f"-layers{args.layers}"
    elif args.presence:
        name += "-presence"
    if args.forecast:
        name += f"-forecast{args.forecast}x{args.stride}"
    if args.labels != 1:
        name += f"-labels{args.labels}"
    rounds = SIZES["tiny" if args.tiny else "default"]["rounds"]
    name = harness.record_name(  # --full is the default size
        name,
        "tiny" if args.tiny else "default",
        rounds=(args.rounds or rounds, rounds),
        hidden=(args.hidden.replace(" ", "").replace(",", "x"), "128x128x128"),
        run=(Path(args.run), DEFAULT_RUN),
    )
    return name + (f"-seed{args.seed}" if args.seed else "")


def arm_of(config: dict) -> str:
    """A record's arm: its representation, forecast and label scale (not its seed)."""
    enc = config.get("encoder", "mlp")
    if enc != "mlp":
        dim = config.get("dim", 64)
        enc += f" (dim {dim})" if (enc, dim) != ("attention", 64) else ""
        enc += ", tables flat" if config.get("static", "pool") == "flat" else ""
        enc += f", {config['layers']} layer(s)" if config.get("layers") not in (None, 2) else ""
    elif config.get("presence"):
        enc += " + presence"
    arm = enc + (
        f" + forecast {config['forecast']}x{config['stride']}" if config.get("forecast") else ""
    )
    arm += f", {config['labels']}x labels" if config.get("labels", 1) != 1 else ""
    if config.get("rounds", 12) != 12:
        arm += f", {config['rounds']} rounds"
    if config.get("hidden", [128, 128, 128]) != [128, 128, 128]:
        arm += ", hidden " + "x".join(str(h) for h in config["hidden"])
    return arm


def report(folder: Path) -> dict[str, Any]:
    """The arms of the records in `folder` (see the module doc): README.md and report.json."""
    import json
    import sys

    from lab import screen

    if not folder.is_dir():
        raise ValueError(f"{folder}: " + ("not a folder" if folder.exists() else "no such folder"))
    paths = sorted(folder.glob("dagger*.json"))
    if not paths:
        raise ValueError(f"{folder}: no DAgger record (dagger*.json) in this folder")
    arms: dict[str, dict[int, float]] = {}
    samples: dict[str, list[int]] = {}
    blinds: dict[str, dict[int, float]] = {}
    skipped: list[str] = []
    for path in paths:
        try:
            rec = json.loads(path.read_text())
            config, final = rec["config"], rec["results"]["final"]["mean"]
            seed = int(config.get("seed", 0))
            sr, blind = _score(final, "SR"), _score(final, "SR_blind")
            curve = rec["results"].get("curve") or []
            n = int(curve[-1]["samples"]) if curve and "samples" in curve[-1] else None
            run = rec["results"].get("run", run_name(DEFAULT_RUN))
        except (OSError, ValueError, KeyError, TypeError, AttributeError, IndexError) as e:
            raise ValueError(f"{path}: not a DAgger record ({type(e).__name__}: {e})") from e
        if config.get("size") not in ("default", "full"):  # --full is the default size
            skipped.append(path.name)
            continue
        if sr is None:  # the project writes a non-finite value as null
            print(
                f"skipped {path}: results.final.mean.SR is {final.get('SR')!r}, not a score",
                file=sys.stderr,
                flush=True,
            )
            continue
        arm = arm_of(config)
        arm += f", run {run}" if run != run_name(DEFAULT_RUN) else ""
        arms.setdefault(arm, {})[seed] = sr
        if blind is not None:
            blinds.setdefault(arm, {})[seed] = blind
        samples.setdefault(arm, [])
        if n is not None:  # a record without its curve: its label count is not known
            samples[arm].append(n)
    if not arms:
        raise ValueError(f"{folder}: no DAgger record of the default size with a final SR")
    rows = []
    for arm, by_seed in sorted(arms.items()):
        scores = [by_seed[k] for k in sorted(by_seed)]
        base_arm = arm.replace(arm.split(",")[0], "mlp", 1)
        base = [arms[base_arm][k] for k in sorted(arms.get(base_arm, {}))]
        row = {
            "arm": arm,
            "seeds": sorted(by_seed),
            "val_SR": scores,
            **screen.seed_stats(scores, "SR"),
            "labels": samples[arm],
            "val_SR_blind": [blinds.get(arm, {}).get(k) for k in sorted(by_seed)],
            "iqm": screen.iqm(scores) if len(scores) > 1 else None,
            "vs": base_arm,
            "improvement": screen.improvement(scores, base)
            if base and base_arm != arm and len(scores) > 1 and len(base) > 1
            else None,
        }
        rows.append(row)

    def fmt(x: float | None) -> str:
        return "-" if x is None else f"{x:.2f}"

    lines = [
        "# DAgger clones of the MPC by representation",
        "",
        "`python -m lab.diagnostics.dagger --relative --sorted [--encoder attention] [--forecast 5"
        " --stride 2] --seed S --out DIR`, then `python -m lab.diagnostics.dagger --report DIR`"
        " (this page and report.json). The clone alone on the 192 validation tasks of task"
        " seeds 1-8 after 12 DAgger rounds on the 120 training layouts (the same tasks and crowds"
        " for every arm and seed); mean +- standard error over seeds, the worst seed, IQM"
        " [95 % bootstrap interval] and P(a seed of the arm beats a seed of the MLP arm); the"
        " last column scores each seed's clone with nobody in its observation (the people still"
        " collide; `lab.diagnostics.crowd_cause`'s blind condition), '-' where not measured.",
        "",
        "| arm | seeds | val SR per seed | mean +- se | worst | IQM [95 %] | P(improvement) "
        "vs mlp | labels | SR with nobody observed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        iq = r["iqm"]
        pi = r["improvement"]
        lines.append(
            f"| {r['arm']} | {len(r['seeds'])} | {' '.join(f'{x:.2f}' for x in r['val_SR'])} | "
            f"{fmt(r['mean'])} +- {fmt(r['se'])} | {fmt(r['worst'])} | "
            + (f"{iq['value']:.2f} [{iq['ci'][0]:.2f}, {iq['ci'][1]:.2f}]" if iq else "-")
            + " | "
            + (f"{pi['value']:.2f} [{pi['ci'][0]:.2f}, {pi['ci'][1]:.2f}]" if pi else "-")
            + (f" | {min(r['labels'])}-{max(r['labels'])} | " if r["labels"] else " | - | ")
            + " ".join(fmt(x) for x in r["val_SR_blind"])
            + " |"
        )
    (folder / "README.md").write_text("\n".join(lines) + "\n")
    (folder / "report.json").write_text(json.dumps({"arms": rows}, indent=1) + "\n")
    print("\n".join(lines[-len(rows) - 2 :]), flush=True)
    if skipped:
        print(f"left out {len(skipped)} record(s) not of the default size: {', '.join(skipped)}")
    return {"arms": rows}


def _score(final: dict, key: str) -> float | None:
    """A record's final score `key` as a float; None where it is missing or not finite (null,
    as the run records write a non-finite value, or NaN / Infinity, as a record written by
    `json.dumps` holds it), so that a report never averages a NaN into an arm."""
    import math

    x = final.get(key)
    if x is None:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise TypeError(f"results.final.mean.{key} is {x!r}, not a number")
    return float(x) if math.isfinite(x) else None


def check_memory(sz: dict, labels: int, obs_dim: int, horizon: int) -> None:
    """The DAgger data set of the last round (every labelled step of `rounds` rounds of
    `labels` x `train_tasks` tasks, observation and MPC action in float32, held as the rounds'
    arrays and their concatenation on the device) and one round's rollout arrays must fit in
    the free memory: one line naming --labels and --rounds otherwise (`harness.fail`)."""
    from mpcpearl_jax.errors import ConfigError
    from mpcpearl_jax.training.resources import check_fits

    tasks = labels * sz["train_tasks"]
    step = 4 * (obs_dim + 2)  # an observation and its MPC action, float32
    data = 2 * sz["rounds"] * tasks * horizon * step
    rollout = tasks * horizon * (step + 4 * 3)  # + the label, collision and goal flags
    what = f"{sz['rounds']} rounds of {tasks} tasks ({horizon} steps each)"
    try:
        check_fits(data + rollout, f"the DAgger data set of {what}", "--labels, --rounds")
    except ConfigError as e:
        harness.fail(str(e))


def make_rollout(env, bridge, net):
    """`rollout(key, params, tasks [B], beta) -> (obs [T, B, O], mpc action [T, B, 2], label
    mask [T, B], collision [T, B], in_goal [T, B])`: the DAgger mixture, MPC solved every step."""
    import jax
    import jax.numpy as jnp

    from mpcpearl_jax.mpc import SOLVED

    horizon = env.config.horizon

    def rollout(key, params, tasks, beta):
        b = tasks.start.shape[0]
        obs0, state0 = jax.vmap(env.reset)(jax.random.split(key, b), tasks)
        fire = jnp.ones(b, bool)

        def body(carry, k):
            obs, state, dead, mpc = carry
            k_mpc, k_mix, k_noise = jax.random.split(k, 3)
            a_pi = net.apply(params, obs)
            a_pi = jnp.clip(a_pi + NOISE * jax.random.normal(k_noise, a_pi.shape), -1, 1)
            mpc, a_mpc, _, status = bridge.step(mpc, k_mpc, fire, state, tasks, a_pi)
            use = jax.random.uniform(k_mix, (b,)) < beta
            act = jnp.where(use[:, None], a_mpc, a_pi)
            nobs, nstate, _, _, info = jax.vmap(env.step)(jax.random.split(k, b), state, act, tasks)
            label = (status == SOLVED) & ~dead
            dead = dead | info.collision | info.in_goal
            return (nobs, nstate, dead, mpc), (obs, a_mpc, label, info.collision, info.in_goal)

        carry = (obs0, state0, jnp.zeros(b, bool), bridge.init(b))
        (*_, mpc), out = jax.lax.scan(body, carry, jax.random.split(key, horizon))
        bridge.finish(mpc)
        return out

    return jax.jit(rollout)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    import sys

    args_in = sys.argv[1:] if argv is None else list(argv)
    if args_in[:1] == ["--report"]:
        if len(args_in) != 2:
            raise SystemExit("--report: give one folder of DAgger records, and nothing else")
        try:
            return report(Path(args_in[1]))
        except ValueError as e:
            harness.fail(str(e))
    p = harness.common_parser(__doc__.split("\n\n")[0])
    p.add_argument("--run", type=Path, default=DEFAULT_RUN, help="run directory (load_policy)")
    p.add_argument("--relative", action="store_true", help="add env.observe_relative")
    p.add_argument("--sorted", action="store_true", help="add env.observe_sorted")
    p.add_argument("--rounds", type=int, default=None, help="DAgger rounds (default by size)")
    p.add_argument("--hidden", default="128,128,128", help="the clone's hidden sizes")
    p.add_argument(
        "--encoder",
        choices=("mlp", "attention", "deepsets", "sarl"),
        default="mlp",
        help="the clone's input network (a crowd encoder: pearl.crowd_encoder)",
    )
    p.add_argument("--dim", type=int, default=64, help="pearl.crowd_dim of a crowd encoder")
    p.add_argument("--layers", type=int, default=2, help="pearl.crowd_layers (deepsets, sarl)")
    p.add_argument("--static", choices=("pool", "flat"), default="pool", help="pearl.crowd_static")
    p.add_argument(
        "--presence",
        action="store_true",
        help="add env.observe_presence (a crowd encoder always has it)",
    )
    p.add_argument("--forecast", type=int, default=0, help="env.observe_forecast (points ahead)")
    p.add_argument("--stride", type=int, default=1, help="env.forecast_stride (steps per point)")
    p.add_argument("--labels", type=int, default=1, help="tasks per round, x the size's")
    p.add_argument("--seed", type=int, default=0, help="the diagnostic's random seed")
    args = p.parse_args(argv)
    for flag in ("forecast", "seed"):
        if getattr(args, flag) < 0:
            p.error(f"--{flag}: must be >= 0")
    for flag in ("stride", "labels", "dim", "layers"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag}: must be at least 1")
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    sz = dict(SIZES[size])
    if args.rounds is not None:
        if args.rounds < 1:
            p.error("--rounds: must be at least 1")
        sz["rounds"] = args.rounds
    try:
        hidden = tuple(int(h) for h in args.hidden.split(","))
    except ValueError:
        p.error(f"--hidden: comma-separated ints expected, got {args.hidden!r}")
    if min(hidden) < 1:
        p.error(f"--hidden: every size must be at least 1, got {args.hidden!r}")

    import jax
    import jax.numpy as jnp
    import numpy as np
    import optax

    from mpcpearl_jax.envs import make_env, make_tasks, redraw_tasks
    from mpcpearl_jax.errors import ConfigError
    from mpcpearl_jax.mpc import MPCConfig, make_mpc_bridge

    cfg = harness.load_runs("--run", [args.run])[0].config
    overrides = dict(cfg.env_overrides)
    if args.relative:
        overrides["observe_relative"] = True
    if args.sorted:
        overrides["observe_sorted"] = True
    if args.presence:
        overrides["observe_presence"] = True
    if args.encoder != "mlp":
        overrides.update(observe_relative=True, observe_presence=True)
    if args.forecast:
        if not overrides.get("observe_relative"):
            p.error(
                f"--forecast {args.forecast}: the forecast is in the robot's frame; add "
                f"--relative (the run {args.run} does not observe relative positions)"
            )
        overrides.update(observe_forecast=args.forecast, forecast_stride=args.stride)
    try:
        env = make_env(cfg.env, **overrides)
        probe = make_tasks(cfg.env, "val", 1, config=env.config)
        if args.encoder != "mlp":
            from mpcpearl_jax.pearl.networks import PearlConfig, crowd_spec

            layout = env.obs_layout(probe)
            pc = PearlConfig(
                crowd_encoder=args.encoder,
                crowd_dim=args.dim,
                crowd_static=args.static,
                crowd_layers=args.layers,
            )
            crowd = crowd_spec(pc, env.obs_dim(probe), layout)
            net = bc_attention(hidden, crowd)
        else:
            net = bc_mlp(hidden)
    except ConfigError as e:  # the run's observation with these flags
        harness.fail(f"{e} (from --run {args.run} and the flags)")
    ids = np.arange(sz["train_tasks"])
    check_memory(sz, args.labels, env.obs_dim(probe), env.config.horizon)
    val = {ts: make_tasks(cfg.env, "val", ts, config=env.config) for ts in sz["final_seeds"]}
    drive = closed_loop(env, net)
    opt = optax.adam(1e-3)
    loss = lambda prm, x, y: jnp.mean(jnp.sum((net.apply(prm, x) - y) ** 2, -1))  # noqa: E731

    @jax.jit
    def step(prm, st, key, xs, ys, n):
        idx = jax.random.randint(key, (BATCH,), 0, n)
        upd, st = opt.update(jax.grad(loss)(prm, xs[idx], ys[idx]), st)
        return optax.apply_updates(prm, upd), st

    bridge = make_mpc_bridge(env, MPCConfig(**cfg.mpc.to_dict()))
    try:
        rollout = make_rollout(env, bridge, net)
        xs_all, ys_all, curve, prm, st = [], [], [], None, None
        key = jax.random.PRNGKey(args.seed)
        for r in range(sz["rounds"]):
            draws = [  # draw 0 is the one of --labels 1
                redraw_tasks(cfg.env, cfg.task_seed, ids, (1000 * (d + 1), r), config=env.config)
                for d in range(args.labels)
            ]
            tasks = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *draws)
            beta = 1.0 if r == 0 else 0.5**r
            if prm is None:
                first = jax.tree_util.tree_map(lambda a: a[:1], tasks)
                obs0, _ = jax.vmap(env.reset)(jax.random.split(key, 1), first)
                prm = net.init(jax.random.PRNGKey(1 + 7919 * args.seed), obs0)
                st = opt.init(prm)
            key, k = jax.random.split(key)
            (obs, lab, mask, col, goal), roll_s = harness.timed(
                lambda k=k, prm=prm, tasks=tasks, beta=beta: jax.block_until_ready(
                    rollout(k, prm, tasks, beta)
                )
            )
            m = np.asarray(mask)
            xs_all.append(np.asarray(obs)[m])
            ys_all.append(np.asarray(lab)[m])
            xs, ys = jnp.asarray(np.concatenate(xs_all)), jnp.asarray(np.concatenate(ys_all))
            n = xs.shape[0]
            success = np.asarray(goal).any(0) & ~np.asarray(col).any(0)
            for _ in range(sz["fit_steps"]):
                key, sub = jax.random.split(key)
                prm, st = step(prm, st, sub, xs, ys, n)
            res = [drive(prm, val[ts]) for ts in sz["round_seeds"]]
            row = {
                "round": r,
                "beta": beta,
                "samples": int(n),
                "rollout_SR": float(np.mean(success)),
                "fit_error": float(loss(prm, xs[:20000], ys[:20000])),
                "val_SR": float(np.mean([x["SR"] for x in res])),
                "val_CFR": float(np.mean([x["CFR"] for x in res])),
                "rollout_s": roll_s,
            }
            curve.append(row)
            print(
                f"round {r}: beta {beta:.4f}, {n} labelled states, rollout SR "
                f"{row['rollout_SR']:.2f}, fit error {row['fit_error']:.3f}, val SR "
                f"{row['val_SR']:.2f} (task seeds {list(sz['round_seeds'])})",
                flush=True,
            )
    finally:
        bridge.close()
    per_seed = {int(ts): drive(prm, val[ts]) for ts in sz["final_seeds"]}
    pooled = {k: float(np.mean([x[k] for x in per_seed.values()])) for k in ("SR", "CFR")}
    # the same clone with nobody in its observation (the people still collide): what it
    # keeps without seeing anyone is what it does from memory (lab.diagnostics.crowd_cause)
    blind = closed_loop(intervened_env(env.config, blind=True), net)
    blind_seed = {int(ts): blind(prm, val[ts]) for ts in sz["final_seeds"]}
    pooled.update(
        {f"{k}_blind": float(np.mean([x[k] for x in blind_seed.values()])) for k in ("SR", "CFR")}
    )
    n_tasks = sum(int(val[ts].start.shape[0]) for ts in per_seed)
    pooled["SR_stderr"] = float(np.sqrt(pooled["SR"] * (1 - pooled["SR"]) / n_tasks))
    results = {
        "run": run_name(args.run),
        "observation": overrides,
        "parameters": int(sum(np.size(a) for a in jax.tree_util.tree_leaves(prm))),
        "curve": curve,
        "final": {"per_task_seed": per_seed, "blind_per_task_seed": blind_seed, "mean": pooled},
    }
    config = {
        "size": size,
        **{k: list(v) if isinstance(v, range | tuple) else v for k, v in sz.items()},
        "hidden": list(hidden),
        "relative": args.relative,
        "sorted": args.sorted,
        "presence": args.presence or args.encoder != "mlp",
        "encoder": args.encoder,
        "dim": args.dim if args.encoder != "mlp" else None,
        "static": args.static if args.encoder != "mlp" else None,
        "layers": args.layers if args.encoder != "mlp" else None,
        "forecast": args.forecast,
        "stride": args.stride,
        "labels": args.labels,
        "seed": args.seed,
        "noise": NOISE,
        "batch": BATCH,
        "threads": threads,
    }
    harness.write_record(record_name(args), config, results, args.out)  # before the tables
    harness.print_table(
        curve, ["round", "beta", "samples", "rollout_SR", "fit_error", "val_SR"], "DAgger"
    )
    print(
        f"clone alone on val task seeds {list(per_seed)}: SR {pooled['SR']:.2f} +- "
        f"{pooled['SR_stderr']:.2f}, CFR {pooled['CFR']:.2f}; with nobody in its observation "
        f"SR {pooled['SR_blind']:.2f}, CFR {pooled['CFR_blind']:.2f}",
        flush=True,
    )
    return results


if __name__ == "__main__":
    main()
