"""What the MPC does with one row (method §6): its status code, the fallback where its solve is
not safe, and the action the env receives.

A fired row whose solve gives a safe plan applies the plan's first input (`SOLVED`). Otherwise it
falls back (method §6): to its previous plan shifted by one step, where that plan was made at the
previous step (`FALLBACK_PLAN`), else to the policy's action (`FALLBACK_POLICY`). The MPC's
inputs are physical (v, delta); the env's action mapping (`envs.dynamics.to_normalized`) turns
them into normalized actions, and every row the MPC does not act on keeps the policy's action.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import Array

from mpcpearl_jax.envs.dynamics import to_normalized

# per-row status codes (the bridge's `status`)
NOT_FIRED = 0
SOLVED = 1  # the MPC action of a safe solve
FALLBACK_PLAN = 2  # solve failed or unsafe: the previous plan shifted by one step
FALLBACK_POLICY = 3  # solve failed or unsafe and no previous plan: the policy action
STATUS_NAMES = {
    NOT_FIRED: "not_fired",
    SOLVED: "solved",
    FALLBACK_PLAN: "fallback_plan",
    FALLBACK_POLICY: "fallback_policy",
}
NO_PLAN = -10  # the step a row's plan was made at, where it holds none


def shifted(plan: np.ndarray) -> np.ndarray:
    """The plan [..., K, 2] one step on: its inputs from the second on, the last one repeated."""
    return np.concatenate([plan[..., 1:, :], plan[..., -1:, :]], axis=-2)


def row_outcome(
    ok: bool, plan: np.ndarray, warm: np.ndarray | None
) -> tuple[int, np.ndarray | None]:
    """(status, the plan the row holds from now on, or None where the policy acts) of a fired row
    whose solve gave `plan` [K, 2], safe if `ok`; `warm`: its previous plan shifted by one step,
    where that plan was made at the previous step, else None."""
    if ok:
        return SOLVED, plan
    if warm is not None:
        return FALLBACK_PLAN, warm
    return FALLBACK_POLICY, None


def merge_actions(u: Array, status: Array, policy_actions: Array, v_max: float) -> Array:
    """Normalized actions [B, 2]: the MPC's physical inputs u [B, 2] (v, delta) through the env's
    action mapping on the rows it acts on (status `SOLVED` or `FALLBACK_PLAN`), the policy's
    actions [B, 2] elsewhere."""
    has_mpc = (status == SOLVED) | (status == FALLBACK_PLAN)
    return jnp.where(has_mpc[:, None], to_normalized(u, v_max), policy_actions.astype(jnp.float32))
