"""GP-MPC controller: the risk-aware MPC acting at every step (the paper's "GP-MPC" column)."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.types import TaskParams
from mpcpearl_jax.mpc.bridge import Bridge

# normalized action for zero speed, straight wheels (NumPy: importing starts no JAX backend)
BRAKE = np.array([-1.0, 0.0], np.float32)


def make_gp_mpc_rollout(
    env: NavEnv, bridge: Bridge, num_steps: int | None = None
) -> Callable[[Array, TaskParams], dict[str, Array]]:
    """`rollout(key, params) -> traj` for a flat batch of tasks params [B] (jittable).

    MPC fires on every row at every step; where a solve is unsafe and no previous plan exists the
    fallback is braking. traj has a leading batch axis: position [B, T + 1, 2], heading [B, T + 1],
    action [B, T, 2], collision / in_goal / used_mpc [B, T], status [B, T] int32, reward [B, T].
    """
    steps = num_steps or env.config.horizon

    def rollout(key: Array, params: TaskParams) -> dict[str, Array]:
        batch = params.start.shape[0]
        _, state0 = jax.vmap(env.reset)(jax.random.split(key, batch), params)
        fire = jnp.ones(batch, bool)
        brake = jnp.broadcast_to(BRAKE, (batch, 2))

        def body(carry, k):
            state, mpc = carry
            mpc, action, used, status = bridge.step(mpc, k, fire, state, params, brake)
            _, nstate, r, _, info = jax.vmap(env.step)(
                jax.random.split(k, batch), state, action, params
            )
            out = dict(
                action=action,
                reward=r,
                position=info.position,
                heading=nstate.pose[:, 2],
                collision=info.collision,
                in_goal=info.in_goal,
                used_mpc=used,
                status=status,
            )
            return (nstate, mpc), out

        carry0 = (state0, bridge.init(batch))
        (_, mpc), traj = jax.lax.scan(body, carry0, jax.random.split(key, steps))
        bridge.finish(mpc)
        traj = jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), traj)
        traj["position"] = jnp.concatenate([state0.pose[:, None, :2], traj["position"]], axis=1)
        traj["heading"] = jnp.concatenate([state0.pose[:, None, 2], traj["heading"]], axis=1)
        return traj

    return rollout
