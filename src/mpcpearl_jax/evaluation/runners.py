"""The controllers `experiments.evaluate` runs on a task set: a trained policy with the meta-test
protocol, GP-MPC at every step, or the policy with MPC infusion as in training.

`Setup` holds what a command line resolved (the run, its policies, the evaluated tasks, the MPC
settings); each `run_*` returns the arrays of its episodes, [S, N, ...] (seeds, tasks), as
`mpcpearl_jax.evaluation.evaluate.summarize` and `scoring.per_task_metrics` read them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mpcpearl_jax.envs.types import NavConfig, TaskParams
from mpcpearl_jax.mpc.shield import ShieldConfig


@dataclass
class Setup:
    """Everything resolved from the command line and the run directory."""

    controller: str
    env_name: str
    env_config: NavConfig
    split: str
    task_seed: int
    data: str | None
    tasks: TaskParams  # the evaluated tasks [N]
    task_ids: list[int]  # their indices in the split
    figure_ids: list[int]
    out: Path
    label: str
    run: Path | None = None
    run_config: Any = None
    policies: list = field(default_factory=list)  # LoadedPolicy per evaluated seed
    seed_ids: list[int] = field(default_factory=list)
    mpc: dict = field(default_factory=dict)  # MPCConfig overrides
    eps: float | None = None  # policy+mpc: MPC probability on an event
    shield: ShieldConfig | None = None  # policy: test-time safety shield (extension)
    # the paper's scenarios (folder and sha256 of each file) when they are the task source
    scenarios: dict | None = None
    perturbation: str = "none"  # the crowd's timing changed (envs.perturb), e.g. "delay=6"
    grbal: tuple | None = None  # a GrBAL run: (GrbalTrainer, saved model of the evaluated seeds)


def _stacked_params(policies: list) -> dict:
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[p.params for p in policies])


# jitted evaluators by everything that shapes their program, so that --task-seeds compiles the
# protocol once and runs it on every seed's tasks (same shapes, new values)
_EVALUATORS: dict[tuple, Any] = {}


def policy_evaluator(s: Setup, episodes: int, online: bool):
    """The jitted `mpcpearl_jax.evaluation.evaluate.make_evaluator` program for `s`, built once per
    (environment config, networks, protocol) and reused across task sets."""
    from mpcpearl_jax.envs.navigation import NavEnv
    from mpcpearl_jax.evaluation import evaluate as eval_lib

    nets = s.policies[0].nets
    t_update = s.run_config.train.t_update
    key = (s.env_config, nets.cfg, nets.obs_dim, nets.action_dim, episodes, online, t_update)
    key += (s.shield,)
    if key not in _EVALUATORS:
        env = NavEnv(s.env_config)
        _EVALUATORS[key] = eval_lib.make_evaluator(
            env, nets, episodes, online=online, t_update=t_update, shield=s.shield
        )
    return _EVALUATORS[key]


def run_policy(s: Setup, key: jax.Array, episodes: int, online: bool) -> dict:
    """The meta-test protocol through `mpcpearl_jax.evaluation.evaluate.make_evaluator`; arrays [S,
    N, ...]."""
    fn = policy_evaluator(s, episodes, online)
    return jax.device_get(fn(key, _stacked_params(s.policies), s.tasks))


def _status_labels(status: np.ndarray, brake: bool) -> np.ndarray:
    from mpcpearl_jax.mpc import FALLBACK_PLAN, FALLBACK_POLICY, NOT_FIRED, SOLVED

    other = "brake (no safe plan)" if brake else "policy (no safe plan)"
    names = {
        NOT_FIRED: "policy",
        SOLVED: "MPC",
        FALLBACK_PLAN: "MPC (previous plan)",
        FALLBACK_POLICY: other,
    }
    return np.vectorize(names.get, otypes=[object])(status)


def run_gp_mpc(s: Setup, key: jax.Array) -> tuple[dict, dict]:
    """GP-MPC at every step (mpcpearl_jax.mpc.make_gp_mpc_rollout); arrays [1, N, ...]."""
    from mpcpearl_jax.envs.navigation import NavEnv
    from mpcpearl_jax.mpc import MPCConfig, make_gp_mpc_rollout, make_mpc_bridge

    env = NavEnv(s.env_config)
    bridge = make_mpc_bridge(env, MPCConfig(**s.mpc))
    try:
        traj = jax.jit(make_gp_mpc_rollout(env, bridge))(key, s.tasks)
        traj = jax.tree_util.tree_map(np.asarray, jax.block_until_ready(traj))
        stats = bridge.stats()
    finally:
        bridge.close()
    result = {k: traj[k][None] for k in ("position", "heading", "collision", "in_goal")}
    result["return"] = traj["reward"].sum(axis=-1)[None]
    result["used_mpc"] = traj["used_mpc"][None]
    result["acted_by"] = _status_labels(traj["status"][None], brake=True)
    return result, stats


def run_policy_mpc(s: Setup, key: jax.Array, eps: float) -> tuple[dict, dict]:
    """Training-style episodes (`mpcpearl_jax.collection.make_collector`): prior z, stochastic
    policy, the MPC on an event with probability eps; arrays [S, N, ...]."""
    from mpcpearl_jax import collection as collect_lib
    from mpcpearl_jax.envs.navigation import NavEnv
    from mpcpearl_jax.mpc import MPCConfig, make_mpc_bridge

    env = NavEnv(s.env_config)
    nets = s.policies[0].nets
    n_seeds, n = len(s.policies), s.tasks.num_tasks
    bridge = make_mpc_bridge(env, MPCConfig(**s.mpc))
    try:
        collector = collect_lib.make_collector(env, nets, bridge, eps)
        k_z, k_run = jax.random.split(key)
        z = nets.prior_z(k_z, (n_seeds, n))
        tasks = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n_seeds, *x.shape)), s.tasks)
        params = _stacked_params(s.policies)["policy"]
        ep = jax.jit(collector)(k_run, params, z, tasks)
        ep = jax.tree_util.tree_map(np.asarray, jax.block_until_ready(ep))
        stats = bridge.stats()
    finally:
        bridge.close()
    tr = ep.transitions
    # the observation starts with (x, y, heading / pi): see NavEnv.observe
    heading = np.concatenate([tr.obs[..., 2], tr.next_obs[..., -1:, 2]], axis=-1) * np.pi
    result = {
        "position": ep.position,
        "heading": heading,
        "collision": ep.collision,
        "in_goal": ep.in_goal,
        "return": tr.reward.sum(axis=-1),
        "used_mpc": ep.used_mpc,
        "acted_by": np.where(ep.used_mpc, "MPC", "policy").astype(object),
    }
    return result, stats
