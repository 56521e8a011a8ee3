"""Meta-test (Algorithm 2): adaptation over episodes, or online adaptation within one episode.

MPC is off; the policy is deterministic (tanh of the mean). Everything is one jitted program,
vmapped over seeds and test tasks.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.types import TaskParams
from mpcpearl_jax.evaluation import metrics
from mpcpearl_jax.mpc.shield import ShieldConfig, shield_step
from mpcpearl_jax.pearl.networks import Networks
from mpcpearl_jax.pearl.types import Transitions, context_from

EVAL_SEED = 12345  # the trainer's evaluation key: same numbers as the run's results.json


def _episode(
    env: NavEnv,
    nets: Networks,
    params,
    task: TaskParams,
    key: Array,
    ctx: Array,
    mask: Array,
    offset: Array,
    t_update: int | None,
    shield: ShieldConfig | None = None,
):
    """One deterministic episode. Context rows [offset, offset + T) are filled as it runs.

    With t_update, z is re-sampled from the context so far every t_update steps (online);
    otherwise z is sampled once at the start from the context given.
    """
    horizon = env.config.horizon
    k0, k_run = jax.random.split(key)
    # z ~ q(z | masked context so far); the prior N(0, I) while the mask is empty
    z0 = nets.sample_z(params["encoder"], ctx, k0, mask)
    obs0, state0 = env.reset(k0, task)

    def body(carry, xs):
        obs, state, z, ctx, mask = carry
        t, k = xs
        if t_update is not None:
            z_new = nets.sample_z(params["encoder"], ctx, k, mask)
            z = jnp.where((t % t_update == 0) & (t > 0), z_new, z)
        a = nets.act(params["policy"], obs, z, None)
        shielded = jnp.zeros((), bool)
        if shield is not None:  # extension: test-time safety shield (mpcpearl_jax.mpc.shield)
            a, shielded = shield_step(env, state, a, task, shield)
        nobs, nstate, r, _, info = env.step(k, state, a, task)
        row = context_from(Transitions(obs, a, r, nobs, jnp.zeros(())))
        ctx = ctx.at[offset + t].set(row)
        mask = mask.at[offset + t].set(1.0)
        out = (info.position, nstate.pose[2], info.collision, info.in_goal, r, shielded)
        return (nobs, nstate, z, ctx, mask), out

    (_, _, _, ctx, mask), (pos, head, col, goal, rew, shielded) = jax.lax.scan(
        body, (obs0, state0, z0, ctx, mask), (jnp.arange(horizon), jax.random.split(k_run, horizon))
    )
    pos = jnp.concatenate([state0.pose[None, :2], pos], axis=0)
    head = jnp.concatenate([state0.pose[None, 2], head], axis=0)
    return (pos, head, col, goal, rew, shielded), ctx, mask


def make_evaluator(
    env: NavEnv,
    nets: Networks,
    num_adapt_episodes: int = 2,
    online: bool = False,
    t_update: int = 5,
    shield: ShieldConfig | None = None,
):
    """`evaluate(key, params [S], tasks [N]) -> dict` of arrays [S, N, ...]: position [T + 1, 2],
    heading [T + 1], collision [T], in_goal [T], shielded [T] (steps whose action the shield
    replaced; all False without one) and return of the evaluated episode.

    Adaptation mode (paper Table II "X"): z from the prior for episode 1, then from the posterior
    of all transitions so far; the returned episode is number num_adapt_episodes + 1.
    Online mode ("O"): a single episode with z re-inferred every t_update steps.
    With `shield` (extension, `mpcpearl_jax.mpc.shield`) every episode, adaptation ones included,
    executes the shielded action, and the context holds what was executed.
    """
    horizon = env.config.horizon
    n_eps = 1 if online else num_adapt_episodes + 1
    ctx_len = n_eps * horizon
    ctx_dim = nets.context_dim

    def one_task(key, params, task):
        ctx = jnp.zeros((ctx_len, ctx_dim))
        mask = jnp.zeros((ctx_len,))
        out = None
        for e in range(n_eps):
            out, ctx, mask = _episode(
                env,
                nets,
                params,
                task,
                jax.random.fold_in(key, e),
                ctx,
                mask,
                jnp.asarray(e * horizon),
                t_update if online else None,
                shield,
            )
        pos, head, col, goal, rew, shielded = out
        return {
            "position": pos,
            "heading": head,
            "collision": col,
            "in_goal": goal,
            "shielded": shielded,
            "return": jnp.sum(rew),
        }

    def evaluate(key: Array, params, tasks: TaskParams) -> dict:
        n = tasks.start.shape[0]
        keys = jax.random.split(key, n)
        per_seed = lambda p: jax.vmap(one_task, in_axes=(0, None, 0))(keys, p, tasks)
        return jax.vmap(per_seed)(params)

    return jax.jit(evaluate)


def episode_metrics(result: dict, tasks: TaskParams, robot_radius: float) -> metrics.EpisodeMetrics:
    """method §8 ingredients of every evaluated episode, each [S, N] (seeds x tasks)."""
    goal = jnp.broadcast_to(tasks.goal, result["position"].shape[:2] + (2,))
    return metrics.episode_metrics(
        result["position"], result["collision"], result["in_goal"], goal, robot_radius
    )


def summarize(result: dict, tasks: TaskParams, robot_radius: float) -> dict:
    """method §8 metrics per seed [S] plus the mean return, as lists/floats."""
    m = episode_metrics(result, tasks, robot_radius)
    per_seed = {k: jnp.mean(v, axis=-1) for k, v in metrics.metric_values(m).items()}
    per_seed["return"] = jnp.mean(result["return"], axis=-1)
    out: dict[str, Any] = {k: float(jnp.mean(v)) for k, v in per_seed.items()}
    out.update({f"{k}_per_seed": [float(x) for x in v] for k, v in per_seed.items()})
    return out
