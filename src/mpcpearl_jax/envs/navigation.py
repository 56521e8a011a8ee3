"""The pure-functional navigation environment shared by every task family.

`NavEnv(config)` exposes gymnax-style `reset(key, params)` and `step(key, state, action, params)`
for a *single* environment; `vmap` over stacked `TaskParams` runs many tasks, `vmap` over keys many
episodes of one task. People move on precomputed paths (`params.human_pos`), so the step reads
their positions at t and t + 1 and never simulates them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs import observation, physics
from mpcpearl_jax.envs.dynamics import bicycle_step, to_physical
from mpcpearl_jax.envs.types import EnvState, NavConfig, StepInfo, TaskParams

ACTION_DIM = 2


class NavEnv:
    """A navigation task family: robot among moving people and static obstacles."""

    action_dim = ACTION_DIM

    def __init__(self, config: NavConfig):
        if not isinstance(config, NavConfig):
            raise TypeError(f"config must be a NavConfig, got {type(config).__name__}")
        self.config = config

    @property
    def name(self) -> str:
        return self.config.name

    def obs_dim(self, params: TaskParams) -> int:
        return observation.obs_dim(
            self.config, params.human_pos.shape[-2], params.static_lo.shape[-2]
        )

    def obs_layout(self, params: TaskParams) -> list[dict]:
        """The parts of the observation (`envs.observation.layout`)."""
        return observation.layout(
            self.config, params.human_pos.shape[-2], params.static_lo.shape[-2]
        )

    # ------------------------------------------------------------------ API
    def reset(self, key: Array, params: TaskParams) -> tuple[Array, EnvState]:
        """Start an episode at the task's start pose. Returns (obs, state)."""
        del key  # deterministic start (method §3, 4)
        state = EnvState(pose=params.start.astype(jnp.float32), t=jnp.zeros((), jnp.int32))
        return self.observe(state, params), state

    def random_start(self, key: Array, params: TaskParams, tries: int = 32) -> Array:
        """A random start pose [3] for the extension `TrainConfig.explore_start_share`
        (exploring starts; never used by the paper's tasks or at test time).

        Position uniform in the arena shrunk by the robot radius, heading uniform in [-pi, pi).
        A candidate is kept if it neither collides (a table or a person present at t = 0) nor
        lies inside the goal region; the first of `tries` candidates that qualifies is returned,
        and the task's own start if none does.
        """
        cfg = self.config
        k_xy, k_th = jax.random.split(key)
        lo = jnp.asarray(cfg.arena_lo) + cfg.robot_radius
        hi = jnp.asarray(cfg.arena_hi) - cfg.robot_radius
        xy = jax.random.uniform(k_xy, (tries, 2), minval=lo, maxval=hi)
        theta = jax.random.uniform(k_th, (tries,), minval=-jnp.pi, maxval=jnp.pi)
        humans, mask = self.humans_at(params, jnp.zeros((), jnp.int32))
        hit = jax.vmap(lambda p: physics.collides(p, humans, mask, params, cfg))(xy)
        in_goal = jnp.linalg.norm(xy - params.goal, axis=-1) <= cfg.goal_radius
        ok = ~hit & ~in_goal
        i = jnp.argmax(ok)
        pose = jnp.concatenate([xy[i], theta[i][None]]).astype(jnp.float32)
        return jnp.where(ok[i], pose, params.start.astype(jnp.float32))

    def step(
        self, key: Array, state: EnvState, action: Array, params: TaskParams
    ) -> tuple[Array, EnvState, Array, Array, StepInfo]:
        """Apply a normalized action [2] in [-1, 1]^2 (clipped).

        Returns (obs, next_state, reward, done, info); done is True after `horizon` steps.
        There is no early termination (method §2).
        """
        del key
        self._check_action(action)
        cfg = self.config
        t = state.t
        pos = state.pose[:2]
        humans_now, mask_now = self.humans_at(params, t)
        humans_next, mask_next = self.humans_at(params, t + 1)
        event = physics.events(pos, humans_now, mask_now, params.goal, cfg)

        u = to_physical(action, cfg.v_max)
        parked = jnp.linalg.norm(pos - params.goal) <= cfg.robot_radius
        u = u.at[0].set(jnp.where(parked, 0.0, u[0]))
        cand = bicycle_step(state.pose, u, cfg.dt, cfg.wheelbase)
        cand = cand.at[:2].set(physics.clip_to_arena(cand[:2], cfg))
        # Safety violations are counted at the attempted position, so that a blocked collision is
        # penalised exactly like one that would have happened.
        n_d, n_s = physics.safety_violations(cand[:2], humans_next, mask_next, params, cfg)
        collision = physics.collides(cand[:2], humans_next, mask_next, params, cfg)
        next_pose = jnp.where(collision, state.pose, cand)
        r = physics.reward(pos, u, n_d, n_s, next_pose[:2], params.goal, cfg)

        next_state = EnvState(pose=next_pose, t=t + 1)
        done = next_state.t >= cfg.horizon
        info = StepInfo(
            collision=collision,
            in_goal=jnp.linalg.norm(next_pose[:2] - params.goal) <= cfg.goal_radius,
            n_dynamic=n_d,
            n_static=n_s,
            event=event,
            position=next_pose[:2],
        )
        return self.observe(next_state, params), next_state, r, done, info

    # ------------------------------------------------------------- helpers
    def humans_at(self, params: TaskParams, t: Array) -> tuple[Array, Array]:
        """People positions [H, 2] and presence mask [H] at step t (clamped to the horizon)."""
        idx = jnp.clip(t, 0, params.human_pos.shape[0] - 1)
        return params.human_pos[idx], params.human_mask[idx]

    def event(self, state: EnvState, params: TaskParams) -> Array:
        """The MPC trigger at the current state (method §5)."""
        humans, mask = self.humans_at(params, state.t)
        return physics.events(state.pose[:2], humans, mask, params.goal, self.config)

    def normalize_xy(self, p: Array) -> Array:
        return observation.normalize_xy(self.config, p)

    def observe(self, state: EnvState, params: TaskParams) -> Array:
        """Observation in [-1, 1] (`envs.observation.observation`, which `deploy.observe` builds
        from a robot's raw arrays): pose, people (absent ones at (-1, -1)), [people's last-step
        displacement (extension `observe_velocity`)], [static centres], [people, nearest static
        points and goal in the robot's frame (extension `observe_relative`)], [people's
        forecast (extension `observe_forecast`)], [presence (extension `observe_presence`)], [the
        elapsed time 2 t / T - 1 (extension `observe_time`)]. With the extension
        `sensing_radius` a person farther than it from the robot counts as absent throughout.
        With `observe_sorted` the people are listed nearest first in every part."""
        humans, mask = self.humans_at(params, state.t)
        prev, prev_mask = self.humans_at(params, jnp.maximum(state.t - 1, 0))
        lo, hi = params.static_lo, params.static_hi
        return observation.observation(
            self.config, state.pose, state.t, humans, mask, prev, prev_mask, lo, hi, params.goal
        )

    def _check_action(self, action: Array) -> None:
        if jnp.shape(action) != (ACTION_DIM,):
            raise ValueError(
                f"{self.name}.step: action must have shape ({ACTION_DIM},) for one env "
                f"(vmap for batches), got {jnp.shape(action)}"
            )

    def rollout(
        self, key: Array, params: TaskParams, policy, num_steps: int | None = None
    ) -> dict[str, Array]:
        """Roll out `policy(key, obs) -> action` for one episode with `lax.scan`.

        Returns arrays with a leading time axis: obs [T, O], action [T, 2], reward [T],
        position [T + 1, 2], collision [T], in_goal [T], event [T].
        """
        steps = num_steps or self.config.horizon
        obs0, state0 = self.reset(key, params)

        def body(carry, k):
            obs, state = carry
            k_pi, k_env = jax.random.split(k)
            a = policy(k_pi, obs)
            nobs, nstate, r, _, info = self.step(k_env, state, a, params)
            out = dict(
                obs=obs,
                action=a,
                reward=r,
                position=info.position,
                collision=info.collision,
                in_goal=info.in_goal,
                event=info.event,
            )
            return (nobs, nstate), out

        _, traj = jax.lax.scan(body, (obs0, state0), jax.random.split(key, steps))
        traj["position"] = jnp.concatenate([state0.pose[None, :2], traj["position"]], axis=0)
        return traj
