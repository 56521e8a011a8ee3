"""The navigation env behind brax's `Env` interface, so brax's wrappers and trainers run on it.

`BraxNavEnv(env, params)` takes one task (single `TaskParams`) or a task distribution (params
stacked on a leading axis). `reset(rng)` samples a task index uniformly, keeps it in
`state.info["task"]` and the episode state (`EnvState`) in `state.pipeline_state`;
`step(state, action)` steps that task. Rewards, observations and events are exactly those of
`NavEnv`.

Termination: the method has no early termination (method §2), so `done` is always 0 here and an
episode is cut by brax's `EpisodeWrapper` (use `episode_length=env.horizon`, as
`wrap_for_training` does).
brax's `AutoResetWrapper` restores the *first* state of each batch slot, so every slot keeps the
task it drew at reset; a batch of slots covers the task distribution.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

try:  # brax is an optional extra
    from brax.envs import base as brax_base
    from brax.envs.wrappers import training as brax_training
except ImportError as e:
    raise ImportError(
        f'the brax adapter needs brax, an optional extra: pip install -e ".[brax]" (or pip '
        f"install brax) ({e})"
    ) from None

from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.types import TaskParams

METRIC_NAMES = ("collision", "in_goal", "n_dynamic", "n_static", "event")


class BraxNavEnv(brax_base.Env):
    """A `NavEnv` on one task or a task distribution as a `brax.envs.base.Env`.

    Args:
      env: the navigation environment (e.g. `make_env("restaurant")`).
      params: single-task params, or params stacked on a leading task axis [N, ...].
    """

    def __init__(self, env: NavEnv, params: TaskParams):
        if not isinstance(env, NavEnv):
            raise TypeError(f"env must be a NavEnv, got {type(env).__name__}")
        stacked = params.start.ndim == 2
        self.env = env
        self.tasks = params if stacked else jax.tree_util.tree_map(lambda x: x[None], params)
        self.num_tasks = int(self.tasks.start.shape[0])
        self._obs_size = env.obs_dim(self.tasks)

    # ------------------------------------------------------------ brax API
    def reset(self, rng: Array) -> brax_base.State:
        """Sample a task and start an episode. rng: a raw PRNG key [2] (brax convention)."""
        rng, k_task, k_reset = jax.random.split(rng, 3)
        task = jax.random.randint(k_task, (), 0, self.num_tasks)
        params = self.task_params(task)
        obs, env_state = self.env.reset(k_reset, params)
        zero = jnp.zeros((), jnp.float32)
        return brax_base.State(
            pipeline_state=env_state,
            obs=obs,
            reward=zero,
            done=zero,
            metrics={name: zero for name in METRIC_NAMES},
            info={"task": task, "rng": rng},
        )

    def step(self, state: brax_base.State, action: Array) -> brax_base.State:
        """One env step of the state's task. action: [2] normalized in [-1, 1]^2."""
        rng, key = jax.random.split(state.info["rng"])
        params = self.task_params(state.info["task"])
        obs, env_state, reward, _, info = self.env.step(key, state.pipeline_state, action, params)
        # keep entries that wrappers added (brax's trainers add e.g. "reward")
        metrics = dict(state.metrics)
        metrics.update({n: jnp.asarray(getattr(info, n), jnp.float32) for n in METRIC_NAMES})
        return state.replace(
            pipeline_state=env_state,
            obs=obs,
            reward=reward.astype(jnp.float32),
            done=jnp.zeros_like(state.done),
            metrics=metrics,
            info={**state.info, "rng": rng},
        )

    @property
    def observation_size(self) -> int:
        return self._obs_size

    @property
    def action_size(self) -> int:
        return self.env.action_dim

    @property
    def backend(self) -> str:
        return "jax"

    # ------------------------------------------------------------- helpers
    @property
    def horizon(self) -> int:
        """Steps per episode (T); pass it as brax's `episode_length`."""
        return self.env.config.horizon

    def task_params(self, task: Array) -> TaskParams:
        """The params of task index `task` (a traced int is fine)."""
        return jax.tree_util.tree_map(lambda x: x[task], self.tasks)


def wrap_for_training(env: BraxNavEnv, episode_length: int | None = None) -> brax_base.Wrapper:
    """brax's standard training wrappers (Vmap, Episode, AutoReset) with the env's horizon."""
    return brax_training.wrap(env, episode_length=episode_length or env.horizon)
