"""Data collection: whole episodes for many (seed, task, episode) rows at once, with
event-triggered MPC infusion (Algorithm 1, lines 4-17; method §5).

The env batch is one explicit flat axis R_all = seeds x rows so that the MPC bridge sees the whole
batch at once (method §6: one host callback per step with the fired rows; the bridge's carry rides
in the scan's); the policy is evaluated per seed with `vmap` over the seed axis of the
parameters.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.types import TaskParams
from mpcpearl_jax.pearl.networks import Networks
from mpcpearl_jax.pearl.types import Transitions

if TYPE_CHECKING:
    from mpcpearl_jax.mpc.bridge import Bridge


class Episodes(NamedTuple):
    """Collected episodes, shaped [S, R, T, ...] (positions [S, R, T + 1, 2])."""

    transitions: Transitions
    position: Array
    collision: Array
    in_goal: Array
    event: Array
    used_mpc: Array


def rows_of(tasks: TaskParams, task_ids: Array) -> TaskParams:
    """Gather the task params of every row: task_ids [...] -> TaskParams [...]."""
    return jax.tree_util.tree_map(lambda x: x[task_ids], tasks)


def make_collector(
    env: NavEnv,
    nets: Networks,
    bridge: Bridge | None = None,
    eps: float = 0.0,
    deterministic: bool = False,
    mesh=None,
    mark_expert: bool = False,
) -> Callable:
    """Build `collect(key, policy_params [S], z [S, R, L], tasks [S, R], explore=None) ->
    Episodes`.

    With `bridge` (see `mpcpearl_jax.mpc.make_mpc_bridge`) and eps > 0, MPC acts on the rows where
    an event fires and a uniform draw is <= eps (paper Algorithm 1); its (normalized) actions go
    into the episodes unmarked, except for the `used_mpc` log. `explore` [S, R] bool (the
    exploring-starts extension, `TrainConfig.explore_start_share`) starts those rows at
    `env.random_start` instead of the task's start pose. `mesh` (`mpcpearl_jax.distributed`):
    the seed axis, hence the flat rows, is split over its devices; the bridge then runs per
    shard (`MPCBridge.on_mesh`). `mark_expert`: the transitions carry the `used_mpc` log as
    their `expert` mark (1.0 where the MPC acted), for a learner that imitates the MPC
    (`pearl.imitation`).
    """
    horizon = env.config.horizon
    # eps = 0 never calls the MPC: its guard and callback stay out of the program (on a GPU each
    # guard sends its predicate to the host every step)
    bridge = bridge if eps > 0 else None
    if bridge is not None and mesh is not None:
        bridge = bridge.on_mesh(mesh)  # type: ignore[attr-defined]

    def policy_actions(policy_params, obs, z, key):
        # obs [S, R, O], z [S, R, L] -> [S, R, A]
        keys = jax.random.split(key, obs.shape[0])
        act = lambda p, o, zz, k: nets.act(p, o, zz, None if deterministic else k)
        return jax.vmap(act)(policy_params, obs, z, keys)

    def collect(
        key: Array,
        policy_params,
        z: Array,
        tasks: TaskParams,
        explore: Array | None = None,
    ) -> Episodes:
        s, r = z.shape[:2]
        flat = jax.tree_util.tree_map(lambda x: x.reshape((s * r, *x.shape[2:])), tasks)
        obs0, state0 = jax.vmap(env.reset)(jax.random.split(key, s * r), flat)
        if explore is not None:  # extension: exploring starts on these rows
            k_start = jax.random.split(jax.random.fold_in(key, 0x57A7), s * r)
            pose = jax.vmap(env.random_start)(k_start, flat)
            pose = jnp.where(explore.reshape(s * r, 1), pose, state0.pose)
            state0 = state0.replace(pose=pose)
            obs0 = jax.vmap(env.observe)(state0, flat)
        # stamp of this batch of episodes: the bridge forgets plans of earlier batches
        stamp = jax.random.bits(jax.random.fold_in(key, 0x5EED), (2,), jnp.uint32)

        def body(carry, xs):
            obs, state, mpc = carry
            k = xs
            k_pi, k_eps, k_mpc = jax.random.split(k, 3)
            a_pi = policy_actions(policy_params, obs.reshape(s, r, -1), z, k_pi).reshape(s * r, -1)
            fire = jax.vmap(env.event)(state, flat)
            if bridge is not None:  # eps > 0
                fire = fire & (jax.random.uniform(k_eps, (s * r,)) <= eps)
                mpc, a_mpc, used, _ = bridge.step(mpc, k_mpc, fire, state, flat, a_pi)
                action = jnp.where(fire[:, None], a_mpc, a_pi)
                used = used & fire
            else:
                action = a_pi
                used = jnp.zeros((s * r,), bool)
            nobs, nstate, rew, _, info = jax.vmap(env.step)(
                jax.random.split(k, s * r), state, action, flat
            )
            expert = used.astype(jnp.float32) if mark_expert else None
            out = (
                Transitions(obs, action, rew, nobs, jnp.zeros_like(rew), expert),
                info.position,
                info.collision,
                info.in_goal,
                info.event,
                used,
            )
            return (nobs, nstate, mpc), out

        mpc0 = bridge.init(s * r, stamp) if bridge is not None else None
        (_, _, mpc), (tr, pos, col, goal, ev, used) = jax.lax.scan(
            body, (obs0, state0, mpc0), jax.random.split(key, horizon)
        )
        if bridge is not None:
            bridge.finish(mpc)
        pos = jnp.concatenate([state0.pose[None, :, :2], pos], axis=0)
        to_rows = lambda x: jnp.swapaxes(x, 0, 1).reshape((s, r, *x.shape[:1], *x.shape[2:]))
        return Episodes(
            jax.tree_util.tree_map(to_rows, tr),
            to_rows(pos),
            to_rows(col),
            to_rows(goal),
            to_rows(ev),
            to_rows(used),
        )

    return collect
