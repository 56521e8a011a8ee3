"""GrBAL's planner: MPPI on the (adapted) learned model, pure JAX, vmappable over envs.

Why MPPI (model predictive path integral control, Williams et al.) rather than CEM (or the random
shooting of the GrBAL authors' released code): the stage cost of eq. (2) is piecewise constant in
the safety and goal terms, so a derivative-free sampler is needed, and MPPI's exponentially
weighted average of all samples moves the plan smoothly where CEM's hard elite cut throws most
samples away (with the few hundred samples a CPU affords, the elite set of CEM is a dozen
sequences) and random shooting starts from scratch at every step. The previous plan,
shifted by one step, is the mean of the next call (warm start), so one or two MPPI iterations per
step suffice; the mean itself is always one of the samples, so a plan that stays good keeps its
weight from step to step.

The cost of an action sequence is the discounted sum of the stage costs of eq. (2) (the env's
reward with its sign flipped, `physics.reward` and `physics.safety_violations`) along the states
predicted by the model: the people's predicted positions give the n_d term, the task's static
obstacles (known, as GrBAL knows the reward function) the n_s term, the goal the w_g bonus. With
`robot_model = "known"` the robot pose follows the bicycle model of eq. (1) (`dynamics`) and the
model predicts only the people; by default ("learned") the model predicts the robot too, as in
GrBAL.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs import physics
from mpcpearl_jax.envs.dynamics import bicycle_step, to_physical
from mpcpearl_jax.envs.types import NavConfig, TaskParams
from mpcpearl_jax.grbal.config import GrbalConfig
from mpcpearl_jax.grbal.model import DynamicsModel, Normalizer, ObsLayout


def mppi(
    cost_fn: Callable[[Array], Array],
    mean: Array,
    key: Array,
    *,
    num_samples: int,
    iterations: int,
    noise_std: float,
    temperature: float,
    low: float = -1.0,
    high: float = 1.0,
) -> tuple[Array, Array]:
    """Minimise `cost_fn(U [N, H, A]) -> [N]` over action sequences in the box [low, high].

    Each iteration samples U_n = clip(mean + noise_std * eps_n) (eps_0 = 0: the mean itself),
    weights w_n = softmax(-(J_n - min J) / temperature) and sets mean = sum_n w_n U_n.
    Returns (mean [H, A], best sampled cost of the last iteration).
    """

    def body(carry, k):
        mean, _ = carry
        eps = noise_std * jax.random.normal(k, (num_samples, *mean.shape))
        eps = eps.at[0].set(0.0)
        u = jnp.clip(mean[None] + eps, low, high)
        j = cost_fn(u)
        j = jnp.where(jnp.isfinite(j), j, jnp.inf)
        w = jax.nn.softmax(-(j - jnp.min(j)) / temperature)
        return (jnp.einsum("n,nha->ha", w, u), jnp.min(j)), None

    (mean, best), _ = jax.lax.scan(
        body, (mean, jnp.zeros((), mean.dtype)), jax.random.split(key, iterations)
    )
    return mean, best


def shift(mean: Array) -> Array:
    """Warm start for the next step: drop the first action, repeat the last."""
    return jnp.concatenate([mean[1:], mean[-1:]], axis=0)


def denormalize_xy(o: Array, cfg: NavConfig) -> Array:
    """Inverse of `NavEnv.normalize_xy`: observation coordinates in [-1, 1] to metres."""
    lo, hi = jnp.asarray(cfg.arena_lo), jnp.asarray(cfg.arena_hi)
    return lo + 0.5 * (o + 1.0) * (hi - lo)


def normalize_xy(p: Array, cfg: NavConfig) -> Array:
    lo, hi = jnp.asarray(cfg.arena_lo), jnp.asarray(cfg.arena_hi)
    return jnp.clip(2.0 * (p - lo) / (hi - lo) - 1.0, -1.0, 1.0)


class Planner:
    """`plan(params, norm, obs, mean, task, key) -> (action, next mean)` for one env.

    params are the (adapted) model parameters; obs the current observation [O]; mean the warm
    start [H, 2] (zeros at the start of an episode); task the env's `TaskParams` (goal and static
    obstacles for eq. 2). Pure JAX: vmap it over envs, jit the caller.
    """

    def __init__(
        self,
        model: DynamicsModel,
        env_cfg: NavConfig,
        *,
        horizon: int,
        num_samples: int,
        iterations: int,
        noise_std: float,
        temperature: float,
        gamma: float,
        robot_model: str = "learned",
    ):
        self.model = model
        self.layout: ObsLayout = model.layout
        self.env_cfg = env_cfg
        self.horizon = horizon
        self.num_samples, self.iterations = num_samples, iterations
        self.noise_std, self.temperature = noise_std, temperature
        self.gamma = gamma
        self.known_robot = robot_model == "known"

    @classmethod
    def from_config(cls, model: DynamicsModel, env_cfg: NavConfig, g: GrbalConfig) -> Planner:
        """The planner of a `GrbalConfig` (horizon, samples, MPPI iterations, noise, ...)."""
        return cls(
            model,
            env_cfg,
            horizon=g.plan_horizon,
            num_samples=g.num_samples,
            iterations=g.mppi_iterations,
            noise_std=g.noise_std,
            temperature=g.temperature,
            gamma=g.gamma,
            robot_model=g.robot_model,
        )

    def initial_mean(self) -> Array:
        return jnp.zeros((self.horizon, 2))

    def _people(self, obs: Array) -> Array:
        h = self.layout.num_humans
        xy = obs[..., 3 : 3 + 2 * h].reshape(obs.shape[:-1] + (h, 2))
        return denormalize_xy(xy, self.env_cfg)

    def sequence_cost(
        self, params, norm: Normalizer, obs: Array, actions: Array, task: TaskParams
    ) -> Array:
        """Discounted sum over the horizon of the eq. (2) stage costs along the predicted states,
        for one action sequence [H, 2] (normalized actions)."""
        cfg = self.env_cfg
        h = self.layout.num_humans
        # absent people are observed at (-1, -1); they stay absent over the short horizon
        present = ~jnp.all(obs[3 : 3 + 2 * h].reshape(h, 2) <= -1.0, axis=-1)
        pose0 = jnp.concatenate([denormalize_xy(obs[:2], cfg), jnp.pi * obs[2:3]])

        def step(carry, a):
            o, pose = carry
            nxt = self.model.predict(params, norm, o, a)
            u = to_physical(a, cfg.v_max)
            if self.known_robot:  # eq. (1) for the robot, the model for the people
                npose = bicycle_step(pose, u, cfg.dt, cfg.wheelbase)
                npose = npose.at[:2].set(physics.clip_to_arena(npose[:2], cfg))
                nxt = nxt.at[:2].set(normalize_xy(npose[:2], cfg)).at[2].set(npose[2] / jnp.pi)
            else:
                npose = jnp.concatenate([denormalize_xy(nxt[:2], cfg), jnp.pi * nxt[2:3]])
            n_d, n_s = physics.safety_violations(npose[:2], self._people(nxt), present, task, cfg)
            r = physics.reward(pose[:2], u, n_d, n_s, npose[:2], task.goal, cfg)
            return (nxt, npose), -r

        _, costs = jax.lax.scan(step, (obs, pose0), actions)
        disc = self.gamma ** jnp.arange(actions.shape[0])
        return jnp.sum(disc * costs)

    def plan(
        self, params, norm: Normalizer, obs: Array, mean: Array, task: TaskParams, key: Array
    ) -> tuple[Array, Array]:
        """One MPPI solve from the warm start `mean`: (first action [2], shifted plan [H, 2])."""
        cost = jax.vmap(lambda u: self.sequence_cost(params, norm, obs, u, task))
        new_mean, _ = mppi(
            cost,
            mean,
            key,
            num_samples=self.num_samples,
            iterations=self.iterations,
            noise_std=self.noise_std,
            temperature=self.temperature,
        )
        return new_mean[0], shift(new_mean)
