"""Env steps/s: the jitted, vmapped restaurant env vs. a NumPy env stepped in a Python loop.

Two measurements, each side by side in one run:

1. Random actions. JAX: `jit(scan over the episode of vmap(env.step))` at batch sizes 1..16384
   (one env per batch row, tasks cycled over the 120 training tasks). Baselines: the NumPy twin
   (`mpcpearl_jax.envs.numpy_ref.NumpyNavEnv`) stepped one env at a time in a Python loop, and
   the jitted single-env JAX step called from a Python loop.
2. Policy in the loop: a tanh-Gaussian MLP of the paper's size (3 x 300, input obs + latent z)
   acting at every step. JAX: inside the same scan, batched. Baselines: the NumPy env in a Python
   loop with the policy evaluated per step (the jitted flax policy at batch 1, and, when PyTorch
   is installed, the same network in PyTorch as in the authors' code).

Compile time (lower + compile) is reported separately and excluded from steps/s. The crossover
is the smallest batch at which the JAX rollout beats the Python loop; break-even steps is how
many env steps it takes before JAX *including its compile time* is ahead.

    python -m benchmarks.env_throughput [--tiny | --full] [--out DIR] [--threads N]
"""

from __future__ import annotations

import time
from typing import Any

from benchmarks import harness

SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(env_batches=(8,), policy_batches=(8,), loop_episodes=2, repeats=2, sample_s=0.02),
    "default": dict(
        env_batches=(1, 16, 256, 1024, 4096, 16384),
        policy_batches=(1, 16, 256, 1024, 4096),
        loop_episodes=20,
        repeats=5,
        sample_s=0.3,
    ),
    "full": dict(
        env_batches=(1, 4, 16, 64, 256, 1024, 4096, 16384),
        policy_batches=(1, 16, 64, 256, 1024, 4096, 16384),
        loop_episodes=60,
        repeats=7,
        sample_s=0.5,
    ),
}
HIDDEN = (300, 300, 300)
LATENT_DIM = 10


# ---------------------------------------------------------------------------- policy
def make_policy(obs_dim: int, action_dim: int):
    """(flax module, params, act(params, obs [N, O], z [N, Z], key) -> action [N, A])."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    class TanhGaussianMLP(nn.Module):
        @nn.compact
        def __call__(self, x):
            for h in HIDDEN:
                x = nn.relu(nn.Dense(h)(x))
            mean, log_std = jnp.split(nn.Dense(2 * action_dim)(x), 2, axis=-1)
            return mean, jnp.clip(log_std, -20.0, 2.0)

    net = TanhGaussianMLP()
    params = net.init(jax.random.key(0), jnp.zeros((1, obs_dim + LATENT_DIM)))

    def act(params, obs, z, key):
        mean, log_std = net.apply(params, jnp.concatenate([obs, z], axis=-1))
        return jnp.tanh(mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape))

    return net, params, act


def torch_policy(obs_dim: int, action_dim: int):
    """The same network in PyTorch: act(obs [O] numpy, z [Z] numpy) -> action [A] numpy."""
    import torch

    from benchmarks.torch_pearl import mlp

    net = mlp(obs_dim + LATENT_DIM, HIDDEN, 2 * action_dim)

    def act(obs, z):
        with torch.no_grad():
            x = torch.from_numpy(obs).float()[None]
            out = net(torch.cat([x, torch.from_numpy(z)[None]], dim=1))
            mean, log_std = out.chunk(2, dim=-1)
            std = log_std.clamp(-20.0, 2.0).exp()
            return torch.tanh(mean + std * torch.randn_like(mean))[0].numpy()

    return act


# ------------------------------------------------------------------------ JAX rollout
def make_jax_rollout(env, num_tasks: int, batch: int, policy_act=None):
    """Jitted `run(key, tasks, policy_params) -> summed reward [batch]`: one episode per row."""
    import jax
    import jax.numpy as jnp

    horizon = env.config.horizon
    task_idx = jnp.arange(batch) % num_tasks
    step = jax.vmap(env.step, in_axes=(None, 0, 0, 0))
    reset = jax.vmap(env.reset, in_axes=(None, 0))

    def run(key, tasks, policy_params):
        params = jax.tree_util.tree_map(lambda x: x[task_idx], tasks)
        k_reset, k_z, k_steps = jax.random.split(key, 3)
        obs, state = reset(k_reset, params)
        z = jax.random.normal(k_z, (batch, LATENT_DIM))

        def body(carry, k):
            obs, state, ret = carry
            if policy_act is None:
                a = jax.random.uniform(k, (batch, env.action_dim), minval=-1.0, maxval=1.0)
            else:
                a = policy_act(policy_params, obs, z, k)
            obs, state, r, _, _ = step(k, state, a, params)
            return (obs, state, ret + r), None

        carry = (obs, state, jnp.zeros((batch,), jnp.float32))
        (_, _, ret), _ = jax.lax.scan(body, carry, jax.random.split(k_steps, horizon))
        return ret

    return jax.jit(run)


def bench_jax(env, tasks, batch, cfg, policy=None) -> dict[str, Any]:
    """Compile, calibrate and time one batch size; steps/s from the median sample."""
    import jax

    act, pparams = policy if policy is not None else (None, None)
    run = make_jax_rollout(env, tasks.num_tasks, batch, act)
    key = jax.random.key(1)
    compiled, compile_s = harness.timed(lambda: run.lower(key, tasks, pparams).compile())
    call = lambda: compiled(key, tasks, pparams)
    _, once = harness.timed(lambda: jax.block_until_ready(call()))
    t = harness.time_fn(
        call,
        repeats=cfg["repeats"],
        warmup=1,
        block=jax.block_until_ready,
        inner=harness.calls_for(once, cfg["sample_s"]),
    )
    steps = batch * env.config.horizon
    return {
        "batch": batch,
        "compile_s": compile_s,
        "steps_per_call": steps,
        "steps_per_s": steps / t["median_s"],
        "steps_per_s_p25_p75": [steps / t["p75_s"], steps / t["p25_s"]],
        "timing": t,
    }


# ----------------------------------------------------------------------- Python loops
def bench_loop(name: str, episode_fn, episodes: int, horizon: int, repeats: int) -> dict[str, Any]:
    """Time `episode_fn(i)` (one episode of `horizon` steps) over `episodes` episodes."""
    episode_fn(0)  # warm-up (and the jit compilation of a per-step JAX function)
    t = harness.time_fn(lambda: [episode_fn(i) for i in range(episodes)], repeats=repeats)
    steps = episodes * horizon
    return {
        "impl": name,
        "batch": 1,
        "steps_per_call": steps,
        "steps_per_s": steps / t["median_s"],
        "steps_per_s_p25_p75": [steps / t["p75_s"], steps / t["p25_s"]],
        "timing": t,
    }


def loop_baselines(env, tasks, cfg, policy, with_torch: bool) -> dict[str, dict[str, Any]]:
    """NumPy env (random / jitted flax policy / torch policy) and the jitted JAX step, looped."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from mpcpearl_jax.envs.numpy_ref import NumpyNavEnv, task_to_numpy

    n, horizon = tasks.num_tasks, env.config.horizon
    np_envs = [NumpyNavEnv(env.config, task_to_numpy(tasks, i)) for i in range(n)]
    rng = np.random.default_rng(0)
    z = rng.standard_normal(LATENT_DIM).astype(np.float32)

    def numpy_episode(i, act):
        e = np_envs[i % n]
        obs = e.reset()
        for _ in range(horizon):
            obs, _, _, _ = e.step(act(obs))

    random_act = lambda obs: rng.uniform(-1.0, 1.0, 2)
    act_fn, pparams = policy
    base_key = jax.random.key(2)
    flax_act = jax.jit(
        lambda p, o, i: act_fn(p, o[None], jnp.asarray(z)[None], jax.random.fold_in(base_key, i))[0]
    )
    calls = iter(range(2**31 - 1))

    def flax_policy(obs):
        return np.asarray(flax_act(pparams, jnp.asarray(obs, jnp.float32), next(calls)))

    step1 = jax.jit(env.step)
    single = [jax.tree_util.tree_map(lambda x, i=i: x[i], tasks) for i in range(min(n, 8))]
    k0 = jax.random.key(0)

    def jax_step_episode(i):
        params = single[i % len(single)]
        obs, state = env.reset(k0, params)
        for _ in range(horizon):
            a = jnp.asarray(rng.uniform(-1.0, 1.0, 2), jnp.float32)
            obs, state, _, _, _ = step1(k0, state, a, params)
        jax.block_until_ready(obs)

    ep, rep = cfg["loop_episodes"], cfg["repeats"]
    out = {
        "numpy_loop": bench_loop(
            "numpy_loop", lambda i: numpy_episode(i, random_act), ep, horizon, rep
        ),
        "jax_step_python_loop": bench_loop(
            "jax_step_python_loop", jax_step_episode, max(1, ep // 4), horizon, rep
        ),
        "numpy_loop_flax_policy": bench_loop(
            "numpy_loop_flax_policy",
            lambda i: numpy_episode(i, flax_policy),
            max(1, ep // 2),
            horizon,
            rep,
        ),
    }
    if with_torch:
        t_act = torch_policy(env.obs_dim(single[0]), env.action_dim)
        out["numpy_loop_torch_policy"] = bench_loop(
            "numpy_loop_torch_policy",
            lambda i: numpy_episode(i, lambda o: t_act(o, z)),
            max(1, ep // 2),
            horizon,
            rep,
        )
    return out


# ----------------------------------------------------------------------------- report
def crossover(rows: list[dict[str, Any]], baseline_rate: float) -> dict[str, Any]:
    """Smallest batch beating the baseline, and per-batch break-even steps incl. compile."""
    first = next((r["batch"] for r in rows if r["steps_per_s"] > baseline_rate), None)
    for r in rows:
        r["speedup"] = r["steps_per_s"] / baseline_rate
        gain = 1.0 / baseline_rate - 1.0 / r["steps_per_s"]  # seconds saved per env step
        r["break_even_steps"] = r["compile_s"] / gain if gain > 0 else None
    return {"crossover_batch": first, "baseline_steps_per_s": baseline_rate}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = harness.common_parser(__doc__.split("\n\n")[0]).parse_args(argv)
    threads = harness.configure_threads(args.threads)
    size = harness.size_of(args)
    cfg = SIZES[size]
    with_torch = harness.torch_threads(threads["threads"]) is not None
    if not with_torch:
        print(harness.TORCH_MISSING, flush=True)

    import jax

    from mpcpearl_jax import make_env, make_tasks

    env = make_env("restaurant")
    tasks = make_tasks("restaurant", "train")
    obs_dim = env.obs_dim(jax.tree_util.tree_map(lambda x: x[0], tasks))
    _, pparams, act = make_policy(obs_dim, env.action_dim)

    t0 = time.perf_counter()
    loops = loop_baselines(env, tasks, cfg, (act, pparams), with_torch)
    env_rows = [bench_jax(env, tasks, b, cfg) for b in cfg["env_batches"]]
    pol_rows = [bench_jax(env, tasks, b, cfg, (act, pparams)) for b in cfg["policy_batches"]]
    env_cross = crossover(env_rows, loops["numpy_loop"]["steps_per_s"])
    pol_cross = crossover(pol_rows, loops["numpy_loop_flax_policy"]["steps_per_s"])
    wall = time.perf_counter() - t0

    cols = ["impl", "batch", "steps_per_s", "speedup", "compile_s", "break_even_steps"]
    base_rows = [{k: v for k, v in r.items() if k != "timing"} for r in loops.values()]
    harness.print_table(base_rows, cols[:3], "Python-loop baselines (1 env, steps/s)")
    for r in env_rows:
        r["impl"] = "jax scan+vmap, random actions"
    for r in pol_rows:
        r["impl"] = "jax scan+vmap, policy 3x300"
    harness.print_table(env_rows, cols, "Random actions: speedup vs numpy_loop")
    harness.print_table(pol_rows, cols, "Policy in the loop: speedup vs numpy_loop_flax_policy")
    best = max(r["steps_per_s"] for r in env_rows)
    summary = {
        "env_crossover": env_cross,
        "policy_crossover": pol_cross,
        "max_env_steps_per_s": best,
        "max_env_speedup_vs_numpy": best / loops["numpy_loop"]["steps_per_s"],
        "max_policy_steps_per_s": max(r["steps_per_s"] for r in pol_rows),
        "targets": {
            "env_steps_per_s>=2e6": best >= 2e6,
            "speedup_vs_numpy>=100": best / loops["numpy_loop"]["steps_per_s"] >= 100,
        },
        "wall_s": wall,
    }
    print(
        f"max env steps/s {best:,.0f} ({summary['max_env_speedup_vs_numpy']:.0f}x numpy loop); "
        f"crossover batch (random) {env_cross['crossover_batch']}, "
        f"(policy) {pol_cross['crossover_batch']}",
        flush=True,
    )
    results = {"loops": loops, "jax_env": env_rows, "jax_policy": pol_rows, "summary": summary}
    config = {
        "size": size,
        **cfg,
        "threads": threads,
        "horizon": env.config.horizon,
        "num_tasks": tasks.num_tasks,
        "obs_dim": obs_dim,
        "policy_hidden": HIDDEN,
        "latent_dim": LATENT_DIM,
    }
    harness.write_record("env_throughput", config, results, args.out)
    return results


if __name__ == "__main__":
    main()
