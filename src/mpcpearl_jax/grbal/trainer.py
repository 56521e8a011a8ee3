"""GrBAL meta-training and meta-test for many seeds in one program.

`GrbalTrainer(cfg)` builds the env, tasks, model, planner and the jitted phases:
  * collection: whole episodes for seeds x rows at once (`lax.scan` over the steps, `vmap` over
    the rows), each step adapting the model from the last M transitions of the episode (one inner
    SGD step) and planning with MPPI on it, plus exploration noise; the initial collection uses
    uniform random actions. Episodes go into per-task buffers (`pearl.buffers`).
  * the fit: the normalization statistics from the buffers, then `updates_per_iteration` outer
    Adam steps on windows of M past + K future transitions as one `lax.scan`;
  * meta-test with the protocol of the other methods (method §7, Algorithm 2): "adapt" runs
    `eval_adapt_episodes` episodes (GrBAL adapting online, as it acts), then adapts the model once
    on all their transitions and reports the next episode with that model fixed (no adaptation
    within it, like the "X" column of the paper's Table II); "online" is one episode adapting at
    every step from the last M transitions (GrBAL's own mode), which is the first of those
    adaptation episodes, so one program gives both.
The whole `GrbalState` is a pytree with a leading seed axis, checkpointed by
`mpcpearl_jax.training.checkpoint`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax import Array

from mpcpearl_jax.envs import make_env, tasks_for
from mpcpearl_jax.envs.types import TaskParams
from mpcpearl_jax.errors import ConfigError, TrainingDiverged
from mpcpearl_jax.evaluation import evaluate as eval_lib
from mpcpearl_jax.evaluation.evaluate import EVAL_SEED
from mpcpearl_jax.grbal.config import GrbalExperimentConfig
from mpcpearl_jax.grbal.model import (
    DynamicsModel,
    Normalizer,
    fit_normalizer,
    identity_normalizer,
    layout_of,
    make_meta_step,
    sample_windows,
)
from mpcpearl_jax.grbal.planner import Planner
from mpcpearl_jax.pearl import buffers
from mpcpearl_jax.pearl.types import Transitions
from mpcpearl_jax.training.protocol import split_keys


class GrbalState(struct.PyTreeNode):
    """Everything that evolves during training; every leaf has a leading seed axis [S]."""

    params: Any
    opt_state: Any
    norm: Normalizer
    buffer: buffers.TaskBuffer
    key: Array
    iteration: Array  # [S] int32 completed iterations


class GrbalTrainer:
    """Builds everything for a GrBAL run; see the module docstring."""

    def __init__(self, cfg: GrbalExperimentConfig):
        self.cfg = cfg
        g = cfg.grbal
        self.env = make_env(cfg.env, **cfg.env_overrides)
        self.train_tasks = tasks_for(cfg, "train", config=self.env.config)
        self.test_tasks = tasks_for(cfg, "test", config=self.env.config)
        self.num_train = int(self.train_tasks.start.shape[0])
        self.horizon = self.env.config.horizon
        if g.past + g.future > self.horizon:
            raise ConfigError(
                f"GrbalConfig.future: past + future ({g.past + g.future}) must not exceed the "
                f"episode length {self.horizon}"
            )
        if g.plan_horizon > self.horizon:  # MPPI plans at most one episode ahead
            raise ConfigError(
                f"GrbalConfig.plan_horizon: must not exceed the episode length {self.horizon}, "
                f"got {g.plan_horizon}"
            )
        self.layout = layout_of(self.env, self.train_tasks)
        self.obs_dim = self.env.obs_dim(self.train_tasks)
        assert self.layout.obs_dim == self.obs_dim
        self.model = DynamicsModel(self.layout, g.hidden)
        self.planner = Planner.from_config(self.model, self.env.config, g)
        self.optimizer = optax.adam(g.lr)
        self.meta_step = make_meta_step(self.model, g.past, g.inner_lr, self.optimizer)
        self.capacity = g.buffer_episodes * self.horizon
        self.collect_phase = jax.jit(self._collect_phase, static_argnums=2, donate_argnums=0)
        self.update_phase = jax.jit(self._update_phase, donate_argnums=0)
        self._evaluate = jax.jit(self._evaluate_fn())

    # ------------------------------------------------------------------ state
    def init_state(self) -> GrbalState:
        return jax.jit(self._init_state)()

    def _init_state(self) -> GrbalState:
        cfg = self.cfg
        keys = jnp.stack([jax.random.PRNGKey(cfg.seed + s) for s in range(cfg.seeds)])
        keys, sub = split_keys(keys, 1)
        params = jax.vmap(self.model.init)(sub[:, 0])
        opt_state = jax.vmap(self.optimizer.init)(params)
        norm = jax.tree_util.tree_map(
            lambda x: jnp.broadcast_to(x, (cfg.seeds, *x.shape)), identity_normalizer(self.layout)
        )
        buf = buffers.init_buffer(
            self.num_train, self.capacity, self.obs_dim, self.env.action_dim, (cfg.seeds,)
        )
        return GrbalState(params, opt_state, norm, buf, keys, jnp.zeros((cfg.seeds,), jnp.int32))

    # -------------------------------------------------------------- episodes
    def _episode(
        self,
        params,
        fixed_params,
        norm: Normalizer,
        task: TaskParams,
        key: Array,
        explore_std: float | Array,
        random: Array,
        online: Array,
    ) -> dict:
        """One episode of one env. random (a scalar flag, not batched): uniform actions; else
        online: adapt `params` from the last M transitions of the episode at every step (GrBAL),
        or plan with `fixed_params` as given. The flags select with `lax.cond`, so one compiled
        body serves every mode. Returns transitions [T], position [T + 1, 2], collision and
        in_goal [T]."""
        g = self.cfg.grbal
        m = g.past
        obs0, state0 = self.env.reset(key, task)
        od = self.obs_dim
        hist0 = (jnp.zeros((m, od)), jnp.zeros((m, 2)), jnp.zeros((m, od)), jnp.zeros((m,)))

        def act(obs, mean, hist, k_plan, k_noise):
            h_o, h_a, h_n, h_m = hist
            p = jax.lax.cond(
                online,
                lambda: self.model.adapt(params, norm, h_o, h_a, h_n, g.inner_lr, mask=h_m),
                lambda: fixed_params,
            )
            a, mean = self.planner.plan(p, norm, obs, mean, task, k_plan)
            a = jnp.clip(a + explore_std * jax.random.normal(k_noise, (2,)), -1.0, 1.0)
            return a, mean

        def act_random(obs, mean, hist, k_plan, k_noise):
            return jax.random.uniform(k_noise, (2,), minval=-1.0, maxval=1.0), mean

        def body(carry, k):
            obs, st, mean, hist = carry
            k_plan, k_noise, k_env = jax.random.split(k, 3)
            a, mean = jax.lax.cond(random, act_random, act, obs, mean, hist, k_plan, k_noise)
            nobs, nst, r, _, info = self.env.step(k_env, st, a, task)
            push = lambda h, x: jnp.concatenate([h[1:], x[None]], axis=0)  # noqa: E731
            h_o, h_a, h_n, h_m = hist
            hist = (push(h_o, obs), push(h_a, a), push(h_n, nobs), push(h_m, jnp.ones(())))
            out = (obs, a, r, nobs, info.position, info.collision, info.in_goal)
            return (nobs, nst, mean, hist), out

        carry0 = (obs0, state0, self.planner.initial_mean(), hist0)
        _, (o, a, r, no, pos, col, goal) = jax.lax.scan(
            body, carry0, jax.random.split(key, self.horizon)
        )
        return {
            "transitions": Transitions(o, a, r, no, jnp.zeros_like(r)),
            "position": jnp.concatenate([state0.pose[None, :2], pos], axis=0),
            "collision": col,
            "in_goal": goal,
        }

    # ------------------------------------------------------------- collection
    def _collect_phase(
        self, state: GrbalState, task_ids: Array, episodes: int, random: Array
    ) -> tuple[GrbalState, dict]:
        """`episodes` episodes for each task of task_ids [S, k], stored in the buffers; random
        (a traced flag): uniform random actions instead of the planner."""
        g = self.cfg.grbal
        keys, sub = split_keys(state.key, 1)
        rows = jnp.repeat(task_ids, episodes, axis=1)  # [S, R]
        online = jnp.ones((), bool)

        def per_seed(params, norm, rows_s, key):
            tasks = jax.tree_util.tree_map(lambda x: x[rows_s], self.train_tasks)
            ks = jax.random.split(key, rows_s.shape[0])

            def run(t, k):
                return self._episode(params, params, norm, t, k, g.explore_std, random, online)

            return jax.vmap(run)(tasks, ks)

        ep = jax.vmap(per_seed)(state.params, state.norm, rows, sub[:, 0])
        s, k = task_ids.shape
        to_task = lambda x: x.reshape((s, k, episodes * self.horizon, *x.shape[3:]))  # noqa: E731
        per_task = jax.tree_util.tree_map(to_task, ep["transitions"])
        buf = jax.vmap(buffers.insert)(state.buffer, task_ids, per_task)
        tr = ep["transitions"]
        stats = {
            "return": jnp.mean(jnp.sum(tr.reward, axis=-1), axis=-1),  # [S]
            "success": jnp.mean(
                jnp.any(ep["in_goal"], -1) & ~jnp.any(ep["collision"], -1), axis=-1
            ),
            "collision_free": jnp.mean(~jnp.any(ep["collision"], -1), axis=-1),
        }
        return state.replace(buffer=buf, key=keys), stats

    def initial_collection(self, state: GrbalState) -> GrbalState:
        """Random actions on every training task (the data of the first fit): `initial_episodes`
        rounds over the tasks, in chunks of the regular collection's shape so that one compiled
        program serves both (the last chunk of a round wraps round to the first tasks)."""
        g = self.cfg.grbal
        k = min(g.tasks_per_iteration, self.num_train)
        chunks = -(-self.num_train // k)
        order = np.arange(chunks * k) % self.num_train
        for _ in range(g.initial_episodes):
            for c in range(chunks):
                ids = jnp.broadcast_to(jnp.asarray(order[c * k : (c + 1) * k]), (self.cfg.seeds, k))
                state, _ = self.collect_phase(state, ids, g.episodes_per_task, jnp.bool_(True))
        return state

    # ---------------------------------------------------------------- updates
    def _update_phase(self, state: GrbalState) -> tuple[GrbalState, dict]:
        g = self.cfg.grbal
        length = g.past + g.future

        def per_seed(params, opt_state, buf, key):
            valid = jnp.arange(self.capacity)[None, :] < buf.size[:, None]
            norm = fit_normalizer(buf.data, valid, self.layout)

            def body(carry, k):
                params, opt_state = carry
                w = sample_windows(
                    buf, k, self.num_train, g.meta_batch, g.windows, length, self.horizon
                )
                params, opt_state, m = self.meta_step(params, opt_state, norm, w)
                return (params, opt_state), m

            (params, opt_state), ms = jax.lax.scan(
                body, (params, opt_state), jax.random.split(key, g.updates_per_iteration)
            )
            first = jax.tree_util.tree_map(lambda x: x[0], ms)
            last = jax.tree_util.tree_map(jnp.mean, ms)
            return params, opt_state, norm, first, last

        keys, sub = split_keys(state.key, 1)
        params, opt_state, norm, first, mean = jax.vmap(per_seed)(
            state.params, state.opt_state, state.buffer, sub[:, 0]
        )
        losses = {
            "model_pre_loss": mean.pre_loss,
            "model_post_loss": mean.post_loss,
            "model_post_loss_first": first.post_loss,
        }
        return state.replace(params=params, opt_state=opt_state, norm=norm, key=keys), losses

    # -------------------------------------------------------------- iteration
    def iteration(
        self, state: GrbalState, stop: Callable[[], bool] | None = None
    ) -> tuple[GrbalState, dict]:
        """One iteration: (random data first), fit the model, collect with the planner. `stop`
        (`loop.train_loop`'s stop request) is not polled: a stopped GrBAL run finishes the
        iteration under way, which the loop then saves."""
        g = self.cfg.grbal
        log: dict[str, Any] = {}
        t0 = time.perf_counter()
        it = int(state.iteration[0])
        if it == 0:
            state = self.initial_collection(state)
            jax.block_until_ready(state.buffer.size)
        t1 = time.perf_counter()
        state, losses = self.update_phase(state)
        losses = jax.device_get(losses)
        t2 = time.perf_counter()
        bad = [k for k, v in losses.items() if not np.all(np.isfinite(v))]
        if bad:
            raise TrainingDiverged(
                f"non-finite model losses {bad} at iteration {it + 1}; the last good checkpoint "
                "is kept (lower grbal.lr or grbal.inner_lr)"
            )
        keys, sub = split_keys(state.key, 1)
        n = min(g.tasks_per_iteration, self.num_train)
        ids = jax.vmap(lambda k: jax.random.choice(k, self.num_train, (n,), replace=False))(
            sub[:, 0]
        )
        state, stats = self.collect_phase(
            state.replace(key=keys), ids, g.episodes_per_task, jnp.bool_(False)
        )
        stats = jax.device_get(stats)
        t3 = time.perf_counter()
        state = state.replace(iteration=state.iteration + 1)
        log["iteration"] = it + 1
        log["initial_collect_s"] = t1 - t0
        log["update_s"] = t2 - t1
        log["collect_s"] = t3 - t2
        for name in ("return", "success", "collision_free"):
            log[f"train_{name}"] = float(np.mean(stats[name]))
        log.update({k: float(np.mean(v)) for k, v in losses.items()})
        log["buffer_transitions"] = int(np.sum(jax.device_get(state.buffer.size)[0]))
        return state, log

    # ------------------------------------------------------------- evaluation
    def _evaluate_fn(self):
        """`evaluate(key, params [S], norm [S], tasks [N]) -> {"adapt": ..., "online": ...}`,
        each a dict of arrays [S, N, ...]: position [T + 1, 2], collision, in_goal [T], return.

        Per task, `eval_adapt_episodes` + 1 episodes in one `lax.scan`: the first ones adapt
        online (GrBAL acting as usual; the first of them, from an empty history, is the "online"
        result); before the last, the model is adapted once on all their transitions and then
        kept fixed for that episode (the "adapt" result)."""
        g = self.cfg.grbal
        n_adapt, horizon = g.eval_adapt_episodes, self.horizon
        od = self.obs_dim

        def one_task(params, norm, task, key):
            ctx0 = Transitions(
                jnp.zeros((n_adapt * horizon, od)),
                jnp.zeros((n_adapt * horizon, 2)),
                jnp.zeros((n_adapt * horizon,)),
                jnp.zeros((n_adapt * horizon, od)),
                jnp.zeros((n_adapt * horizon,)),
            )

            def body(ctx, e):
                last = e == n_adapt
                fixed = jax.lax.cond(
                    last,
                    lambda: self.model.adapt(
                        params, norm, ctx.obs, ctx.action, ctx.next_obs, g.inner_lr
                    ),
                    lambda: params,
                )
                ep = self._episode(
                    params,
                    fixed,
                    norm,
                    task,
                    jax.random.fold_in(key, e),
                    0.0,
                    jnp.bool_(False),
                    ~last,
                )
                at = jnp.minimum(e, n_adapt - 1) * horizon
                ctx = jax.tree_util.tree_map(
                    lambda c, x: jax.lax.dynamic_update_slice_in_dim(c, x, at, 0),
                    ctx,
                    ep["transitions"],
                )
                out = {
                    "position": ep["position"],
                    "collision": ep["collision"],
                    "in_goal": ep["in_goal"],
                    "return": jnp.sum(ep["transitions"].reward),
                }
                return ctx, out

            _, outs = jax.lax.scan(body, ctx0, jnp.arange(n_adapt + 1))
            pick = lambda i: jax.tree_util.tree_map(lambda x: x[i], outs)  # noqa: E731
            return {"adapt": pick(n_adapt), "online": pick(0)}

        def evaluate(key: Array, params, norm: Normalizer, tasks: TaskParams) -> dict:
            keys = jax.random.split(key, tasks.start.shape[0])
            per_seed = lambda p, nm: jax.vmap(one_task, in_axes=(None, None, 0, 0))(  # noqa: E731
                p, nm, tasks, keys
            )
            return jax.vmap(per_seed)(params, norm)

        return evaluate

    def evaluate_both(
        self, state: GrbalState, tasks: TaskParams | None = None, key: Array | None = None
    ) -> dict:
        """{"adapt": summary, "online": summary} on `tasks` (default: the test tasks) from one
        run of the evaluation program; each summary holds the method §8 metrics (mean and per
        seed)."""
        return self.evaluate_both_episodes(state, tasks, key)[0]

    def evaluate_both_episodes(
        self, state: GrbalState, tasks: TaskParams | None = None, key: Array | None = None
    ) -> tuple[dict, dict]:
        """(`evaluate_both`'s summaries, the evaluated episodes {"adapt": arrays [S, N, ...],
        "online": ...}, for figures)."""
        tasks = self.test_tasks if tasks is None else tasks
        key = jax.random.PRNGKey(EVAL_SEED) if key is None else key
        res = jax.device_get(self._evaluate(key, state.params, state.norm, tasks))
        r = self.env.config.robot_radius
        return {k: eval_lib.summarize(v, tasks, r) for k, v in res.items()}, res

    def rollouts(self, params, norm: Normalizer, tasks: TaskParams, key: Array) -> dict:
        """The evaluation program on saved model parameters and normalisation ([S]-stacked, as
        `model_params` returns them): {"adapt": arrays [S, N, ...], "online": ...}."""
        return jax.device_get(self._evaluate(key, params, norm, tasks))

    def evaluate(
        self,
        state: GrbalState,
        tasks: TaskParams | None = None,
        online: bool = False,
        key: Array | None = None,
    ) -> dict:
        """method §8 metrics after adaptation (or online), as `evaluate_both`."""
        return self.evaluate_both(state, tasks, key)["online" if online else "adapt"]

    def model_params(self, state: GrbalState) -> dict:
        """What `policy.msgpack` holds for a GrBAL run: model parameters and normalization."""
        return jax.device_get({"model": state.params, "norm": state.norm})
