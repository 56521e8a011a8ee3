"""MPC-PEARL meta-training (Algorithm 1) for many seeds in one program.

`Trainer(cfg)` builds the env, tasks, networks, MPC bridge and three jitted phases:
  * collection (prior z and posterior z) over a flat batch of seeds x tasks x episodes, with
    event-triggered MPC through one `pure_callback` per step (only when an event fires);
  * the N_train gradient steps as one `lax.scan`, vmapped over seeds, buffers donated;
  * meta-test evaluation (Algorithm 2), vmapped over seeds and tasks.
With several devices (`cfg.devices`, `mpcpearl_jax.distributed`) the seed axis of every phase is
split over a device mesh; each seed computes what it computes on one device.
The whole `TrainState` (params, optimizer states, target nets, buffers, RNG keys, iteration) is a
pytree, checkpointed by `mpcpearl_jax.training.checkpoint`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import Array

from mpcpearl_jax.config import ExperimentConfig, validate
from mpcpearl_jax.distributed import constrain, first_local, make_mesh, sum_over_processes, to_host
from mpcpearl_jax.envs import make_env, redraw_tasks, tasks_for
from mpcpearl_jax.envs.perturb import delay_people
from mpcpearl_jax.envs.types import TaskParams
from mpcpearl_jax.errors import ConfigError, TrainingDiverged
from mpcpearl_jax.evaluation import evaluate as eval_lib
from mpcpearl_jax.evaluation.runners import EVAL_SEED
from mpcpearl_jax.pearl import buffers
from mpcpearl_jax.pearl.learner import (
    LearnerState,
    acting_params,
    init_learner,
    make_update,
)
from mpcpearl_jax.pearl.networks import Networks
from mpcpearl_jax.pearl.types import context_from
from mpcpearl_jax.training import collect as collect_lib


class IterationAbandoned(Exception):
    """`iteration(state, stop)` stopped early because stop() became true; the state passed in
    was consumed (its buffers donated) and must not be used: restore a checkpoint."""


# gradient steps per jitted update call: the update phase runs in chunks of this many steps (the
# same keys and results as one scan), so a stop request is answered between chunks (~7 s at the
# paper's sizes on a 2-core CPU)
UPDATE_CHUNK = 25


class TrainState(struct.PyTreeNode):
    """Everything that evolves during training; every leaf has a leading seed axis [S]."""

    learner: LearnerState
    rl: buffers.TaskBuffer
    enc: buffers.TaskBuffer
    # MPC transitions kept apart (extension `mpc_buffer_fraction`; None when it is off)
    mpc: buffers.TaskBuffer | None
    tasks: TaskParams  # [S, N, ...] training tasks as collected (redraw_behaviours changes them)
    key: Array  # [S, 2] PRNG keys
    iteration: Array  # [S] int32 completed iterations (0 = only the initial collection pending)


def _split_keys(keys: Array, n: int) -> tuple[Array, Array]:
    """keys [S, 2] -> (new carry keys [S, 2], subkeys [S, n, 2])."""
    both = jax.vmap(lambda k: jax.random.split(k, n + 1))(keys)
    return both[:, 0], both[:, 1:]


class Trainer:
    """Builds everything for an experiment; see module docstring."""

    def __init__(self, cfg: ExperimentConfig):
        self.cfg = cfg
        self.env = make_env(cfg.env, **cfg.env_overrides)
        try:
            self.train_tasks = tasks_for(cfg, "train", config=self.env.config)
            self.test_tasks = tasks_for(cfg, "test", config=self.env.config)
        except (TypeError, ValueError) as e:
            if not cfg.task_options:
                raise
            raise ConfigError(f"ExperimentConfig.task_options: {e}") from e
        self.num_train = int(self.train_tasks.start.shape[0])
        self._task_kw = dict(cfg.task_options)
        validate(cfg)
        self.mesh = make_mesh(cfg.seeds, cfg.devices)  # None: one device, no sharding
        self.obs_dim = self.env.obs_dim(self.train_tasks)
        self.action_dim = self.env.action_dim
        self.nets = Networks(cfg.pearl, self.obs_dim, self.action_dim)
        self.horizon = self.env.config.horizon
        tc = cfg.train
        self.enc_capacity = tc.prior_episodes * self.horizon
        self.bridge = None
        if tc.uses_mpc:
            from mpcpearl_jax.mpc import make_mpc_bridge

            self.bridge = make_mpc_bridge(self.env, cfg.mpc)
        self._collector = collect_lib.make_collector(
            self.env, self.nets, self.bridge, tc.eps, mesh=self.mesh
        )
        self._update_body = make_update(self.nets, jit=False)
        self.collect_phase = jax.jit(
            self._collect_phase, static_argnums=(2, 3, 4, 5), donate_argnums=0
        )
        self.use_mpc_buffer = tc.mpc_buffer_fraction > 0 and tc.uses_mpc
        self.update_phase = jax.jit(self._update_phase, donate_argnums=0)
        self.update_chunk = UPDATE_CHUNK
        self._init_state_jit = jax.jit(self._init_state)
        self._update_steps_jit = jax.jit(self._update_steps, donate_argnums=0)
        self._delay_crowds_jit = jax.jit(self._delay_crowds_impl)
        self.evaluate_adapt = eval_lib.make_evaluator(
            self.env, self.nets, tc.eval_adapt_episodes, online=False
        )
        self.evaluate_online = eval_lib.make_evaluator(
            self.env, self.nets, online=True, t_update=tc.t_update
        )

    # ------------------------------------------------------------------ state
    def init_state(self) -> TrainState:
        """The state before iteration 0 (one jitted program: the same values as built op by op,
        compiled once and kept by the compilation cache, where op by op takes seconds)."""
        return self._init_state_jit()

    def _init_state(self) -> TrainState:
        cfg = self.cfg
        keys = jnp.stack([jax.random.PRNGKey(cfg.seed + s) for s in range(cfg.seeds)])
        keys, sub = _split_keys(keys, 1)
        learner = jax.vmap(lambda k: init_learner(k, self.nets))(sub[:, 0])
        # phases donate their input state: give the learner's aliased leaves (target V = V at
        # init) their own buffers; the replay buffers are created unaliased and at full size once
        learner = jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), learner)
        n, od, ad, lead = self.num_train, self.obs_dim, self.action_dim, (cfg.seeds,)
        rl = buffers.init_buffer(n, cfg.train.rl_capacity, od, ad, lead)
        enc = buffers.init_buffer(n, self.enc_capacity, od, ad, lead)
        mpc = None
        if self.use_mpc_buffer:
            mpc = buffers.init_buffer(n, cfg.train.mpc_buffer_capacity, od, ad, lead)
        tasks = jax.tree_util.tree_map(
            lambda x: jnp.array(jnp.broadcast_to(x, (cfg.seeds, *x.shape))), self.train_tasks
        )
        iteration = jnp.zeros((cfg.seeds,), jnp.int32)
        state = TrainState(learner, rl, enc, mpc, tasks, keys, iteration)
        return constrain(state, self.mesh)

    # ------------------------------------------------------------- collection
    def _row_z(self, state: TrainState, keys: Array, rows: Array, posterior: bool) -> Array:
        """z [S, R, L] per collection row: prior samples, or posterior of sampled context."""
        cfg = self.cfg.pearl

        def per_seed(learner, enc, key, rows_s):
            k_c, k_z = jax.random.split(key)
            if not posterior:  # the prior N(0, I) (z = 0 without an encoder)
                shape = (rows_s.shape[0], cfg.latent_dim)
                return jax.random.normal(k_z, shape) if cfg.use_context else jnp.zeros(shape)
            ctx = context_from(buffers.sample(enc, k_c, rows_s, cfg.context_size))
            return self.nets.sample_z(learner.params["encoder"], ctx, k_z)

        return jax.vmap(per_seed)(state.learner, state.enc, keys, rows)

    def _collect_phase(
        self,
        state: TrainState,
        task_ids: Array,
        episodes: int,
        posterior: bool,
        to_encoder: bool,
        clear_encoder: bool,
    ) -> tuple[TrainState, dict]:
        """Collect `episodes` per task of task_ids [S, k] and store them. Returns (state, stats)."""
        keys, sub = _split_keys(state.key, 2)
        rows = jnp.repeat(task_ids, episodes, axis=1)  # [S, k * E]
        enc = state.enc
        if clear_encoder:
            enc = jax.vmap(buffers.clear)(enc, task_ids)
        state = state.replace(enc=enc)
        z = self._row_z(state, sub[:, 0], rows, posterior)
        tasks = jax.vmap(collect_lib.rows_of)(state.tasks, rows)
        share = self.cfg.train.explore_start_share
        explore = None
        if share > 0 and posterior and not to_encoder:  # extension: exploring starts
            k_explore = jax.random.fold_in(sub[0, 1], 11)
            explore = jax.random.uniform(k_explore, rows.shape) < share
        ep = self._collector(sub[0, 1], state.learner.params["policy"], z, tasks, explore)
        s, k = task_ids.shape
        to_task = lambda x: x.reshape((s, k, episodes * self.horizon, *x.shape[3:]))  # noqa: E731
        per_task = jax.tree_util.tree_map(to_task, ep.transitions)
        rl = jax.vmap(buffers.insert)(state.rl, task_ids, per_task)
        if to_encoder:
            enc = jax.vmap(buffers.insert)(enc, task_ids, per_task)
        mpc = state.mpc
        if self.use_mpc_buffer:
            mpc = jax.vmap(buffers.insert_masked)(mpc, task_ids, per_task, to_task(ep.used_mpc))
        success = jnp.any(ep.in_goal, -1) & ~jnp.any(ep.collision, -1)  # [S, R]
        # episode statistics are over the rows that start at the task's start (all without
        # exploring starts); the exploring ones are counted apart
        x_rows = jnp.zeros(rows.shape) if explore is None else explore.astype(jnp.float32)
        mean_over = lambda w, x: jnp.sum(w * x, -1) / jnp.maximum(jnp.sum(w, -1), 1.0)  # noqa: E731
        on_start = lambda x: mean_over(1.0 - x_rows, x)  # noqa: E731
        stats = {
            "return": on_start(jnp.sum(ep.transitions.reward, axis=-1)),  # [S]
            "success": on_start(success),
            "collision_free": on_start(~jnp.any(ep.collision, -1)),
            "event_rate": jnp.mean(ep.event, axis=(-1, -2)),
            "mpc_share": jnp.mean(ep.used_mpc, axis=(-1, -2)),
            "explore_rows": jnp.mean(x_rows, axis=-1),
            "explore_success": mean_over(x_rows, success),
            "steps": jnp.asarray(ep.transitions.reward[0].size),
        }
        new = state.replace(rl=rl, enc=enc, mpc=mpc, key=keys)
        return constrain(new, self.mesh), stats

    def _choose_tasks(self, state: TrainState, k: int) -> tuple[TrainState, Array]:
        keys, sub = _split_keys(state.key, 1)
        n = self.num_train
        pick = lambda key: jax.random.choice(key, n, (min(k, n),), replace=False)
        return state.replace(key=keys), jax.vmap(pick)(sub[:, 0])

    def _redraw(self, state: TrainState, ids: Array, iteration: int) -> TrainState:
        """Extension `redraw_behaviours`: fresh behaviours for the tasks ids [S, k] about to be
        collected, drawn on the host from a stream fixed by (run seed, seed index, iteration), so
        a resumed run draws the same ones."""
        ids_np = np.asarray(to_host(ids))
        fresh = [
            redraw_tasks(
                self.cfg.env,
                self.cfg.task_seed,
                ids_np[s],
                (self.cfg.seed + s, iteration),
                config=self.env.config,
                **self._task_kw,
            )
            for s in range(ids_np.shape[0])
        ]
        new = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *fresh)  # [S, k, ...]
        seed_ix = jnp.arange(ids_np.shape[0])[:, None]
        tasks = jax.tree_util.tree_map(
            lambda x, y: x.at[seed_ix, ids].set(y.astype(x.dtype)), state.tasks, new
        )
        return state.replace(tasks=tasks)

    def _delay_crowds(self, state: TrainState, ids: Array) -> TrainState:
        """Extension `crowd_delay_max`: the visited tasks ids [S, k] get their people's paths
        with a fresh random delay per person (`envs.perturb.delay_people`), applied to the
        task's own crowd (the one just re-drawn with `redraw_behaviours`, else the original
        training task), so delays never accumulate over visits. Keys come from the run's stream
        in `TrainState`, so a resumed run draws the same delays."""
        return self._delay_crowds_jit(state, ids)

    def _delay_crowds_impl(self, state: TrainState, ids: Array) -> TrainState:
        keys, sub = _split_keys(state.key, 1)
        if self.cfg.train.redraw_behaviours:  # the crowds just re-drawn
            visited = jax.vmap(collect_lib.rows_of)(state.tasks, ids)  # [S, k, ...]
        else:  # the original training tasks
            visited = collect_lib.rows_of(self.train_tasks, ids)
        people = visited.human_pos.shape[-2]
        top = self.cfg.train.crowd_delay_max
        draw = lambda key: jax.random.randint(key, (ids.shape[1], people), 0, top + 1)  # noqa: E731
        delays = jax.vmap(draw)(sub[:, 0])  # [S, k, H]
        new = jax.vmap(delay_people)(visited, delays)
        seed_ix = jnp.arange(ids.shape[0])[:, None]
        tasks = jax.tree_util.tree_map(
            lambda x, y: x.at[seed_ix, ids].set(y.astype(x.dtype)), state.tasks, new
        )
        return constrain(state.replace(tasks=tasks, key=keys), self.mesh)

    # ---------------------------------------------------------------- updates
    def _update_phase(self, state: TrainState) -> tuple[TrainState, dict]:
        """All N_train gradient steps in one scan; -> (state, mean losses [S])."""
        keys, step_keys = self._update_keys(state)
        learner, ms = self._update_steps(state.learner, state.rl, state.enc, state.mpc, step_keys)
        return state.replace(learner=learner, key=keys), jax.tree_util.tree_map(
            lambda x: jnp.mean(x, axis=1), ms
        )

    def _update_keys(self, state: TrainState) -> tuple[Array, Array]:
        """(new carry keys [S, 2], one key per gradient step [S, N_train, 2])."""
        keys, sub = _split_keys(state.key, 1)
        steps = self.cfg.train.updates_per_iteration
        return keys, jax.vmap(lambda k: jax.random.split(k, steps))(sub[:, 0])

    def _chunked_update_phase(
        self, state: TrainState, stop: Callable[[], bool] | None
    ) -> tuple[TrainState, dict]:
        """As `update_phase`, in jitted chunks of `update_chunk` steps over the same keys;
        raises IterationAbandoned between chunks once stop() is true."""
        keys, step_keys = self._update_keys(state)
        steps = int(step_keys.shape[1])
        learner, parts = state.learner, []
        for lo in range(0, steps, self.update_chunk):
            if stop is not None and stop():
                raise IterationAbandoned
            chunk = step_keys[:, lo : lo + self.update_chunk]
            learner, ms = self._update_steps_jit(learner, state.rl, state.enc, state.mpc, chunk)
            parts.append(jax.block_until_ready(ms))  # a stop request waits one chunk at most
        ms = jax.tree_util.tree_map(lambda *x: jnp.mean(jnp.concatenate(x, axis=1), axis=1), *parts)
        return state.replace(learner=learner, key=keys), ms

    def _update_steps(self, learner, rl, enc, mpc, step_keys: Array) -> tuple[Any, dict]:
        """Gradient steps with keys [S, n, 2] (one scan, vmapped over seeds); -> (learner,
        per-step losses [S, n])."""
        cfg, n = self.cfg.pearl, self.num_train

        frac = self.cfg.train.mpc_buffer_fraction
        n_mpc = int(round(cfg.batch_size * frac)) if self.use_mpc_buffer else 0

        def per_seed(learner, rl, enc, mpc, keys):
            def body(learner, k):
                k_t, k_b, k_c, k_u = jax.random.split(k, 4)
                tids = jax.random.choice(k_t, n, (cfg.meta_batch,), replace=cfg.meta_batch > n)
                batch = buffers.sample(rl, k_b, tids, cfg.batch_size)
                ctx = context_from(buffers.sample(enc, k_c, tids, cfg.context_size))
                if n_mpc == 0:
                    return self._update_body(learner, batch, ctx, k_u)
                # extension: the last n_mpc rows of each task's batch come from its MPC buffer
                # (tasks whose MPC buffer is still empty keep their RL rows)
                from_mpc = buffers.sample(mpc, jax.random.fold_in(k_b, 1), tids, n_mpc)
                has = (mpc.size[tids] > 0)[:, None]  # [MB, 1]
                mix = (
                    lambda b, d: b.at[:, -n_mpc:].set(  # noqa: E731
                        jnp.where(has.reshape(has.shape + (1,) * (d.ndim - 2)), d, b[:, -n_mpc:])
                    )
                )
                batch = jax.tree_util.tree_map(mix, batch, from_mpc)
                return self._update_body(learner, batch, ctx, k_u)

            return jax.lax.scan(body, learner, keys)

        out = jax.vmap(per_seed)(learner, rl, enc, mpc, step_keys)
        return constrain(out, self.mesh)

    # -------------------------------------------------------------- iteration
    def initial_collection(self, state: TrainState) -> tuple[TrainState, dict]:
        """Iteration 0: every training task, prior z, RL + encoder buffers."""
        ids = jnp.broadcast_to(jnp.arange(self.num_train), (self.cfg.seeds, self.num_train))
        return self.collect_phase(state, ids, self.cfg.train.initial_episodes, False, True, True)

    def iteration(
        self, state: TrainState, stop: Callable[[], bool] | None = None
    ) -> tuple[TrainState, dict]:
        """One meta-training iteration, Algorithm 1 lines 3-23 (as in the authors' PEARL code):

        - data collection (lines 4-17), for `tasks_per_iteration` training tasks drawn at random:
          `prior_episodes` episodes with z ~ N(0, I) (line 5) that also fill the task's encoder
          buffer, then `posterior_episodes` with z ~ q_phi(z | c) (lines 16-17), every step
          acted by the MPC when an event fires and rand <= eps (lines 8-11; `collect`), else by
          pi_theta (line 13), and stored in the task's replay buffer H^i (line 15);
        - training (lines 18-23): N_train = `updates_per_iteration` gradient steps, each over a
          meta-batch of tasks with a context c^i and a batch B^i (line 20), z^i ~ q_phi (line 21)
          and the losses L_phi, L_theta, L_psi (lines 22-23; `pearl.learner`).

        The extensions (docs/extensions.md) hook in where named: re-drawn or delayed crowds
        before collection, exploring-start rows in it, the MPC buffer in the batches. stop (e.g.
        set by Ctrl-C) is polled before the updates and between update chunks; once true the
        iteration is abandoned with IterationAbandoned (the state passed in is consumed).
        """
        tc = self.cfg.train
        log: dict[str, Any] = {}
        t0 = time.perf_counter()
        if self.bridge is not None:
            self.bridge.reset_stats()
        it = int(first_local(state.iteration))
        if it == 0:
            state, _ = self.initial_collection(state)
        state, ids = self._choose_tasks(state, tc.tasks_per_iteration)
        if tc.redraw_behaviours:
            state = self._redraw(state, ids, it + 1)
        if tc.crowd_delay_max > 0:
            state = self._delay_crowds(state, ids)
        state, prior = self.collect_phase(state, ids, tc.prior_episodes, False, True, True)
        post = None
        if tc.posterior_episodes > 0:
            state, post = self.collect_phase(state, ids, tc.posterior_episodes, True, False, False)
        jax.block_until_ready(state.rl.size)
        t1 = time.perf_counter()
        state, losses = self._chunked_update_phase(state, stop)
        losses = to_host(losses)
        t2 = time.perf_counter()
        bad = [k for k, v in losses.items() if not np.all(np.isfinite(v))]
        if bad:
            raise TrainingDiverged(
                f"non-finite losses {bad} at iteration {it + 1}; "
                "the last good checkpoint is kept (lower the learning rate or reward scale)"
            )
        state = state.replace(iteration=state.iteration + 1)
        log["iteration"] = it + 1
        log["collect_s"] = t1 - t0
        log["update_s"] = t2 - t1
        src = post if post is not None else prior
        names = (
            "return",
            "success",
            "collision_free",
            "event_rate",
            "mpc_share",
            "explore_rows",
            "explore_success",
        )
        src, prior_ret = to_host(({n: src[n] for n in names}, prior["return"]))
        for name in names:
            log[f"train_{name}"] = float(np.mean(src[name]))
        log["train_prior_return"] = float(np.mean(prior_ret))
        if self.bridge is not None:
            st = self.bridge.stats()
            # counters and times summed over processes (each solves its own shards' rows);
            # the reasons are this process's
            calls, rows, fallbacks, solve_s, host_s = sum_over_processes(
                [
                    st["calls"],
                    st["rows_solved"],
                    st["fallbacks"],
                    float(sum(st["solve_s"])),
                    float(sum(st["host_call_s"])),
                ]
            )
            log["mpc_calls"] = int(calls)
            log["mpc_rows"] = int(rows)
            log["mpc_fallbacks"] = int(fallbacks)
            log["mpc_fallback_rate"] = float(fallbacks) / max(int(rows), 1)
            log["mpc_reasons"] = st["reasons"]
            log["mpc_solve_s"] = float(solve_s)
            log["mpc_host_s"] = float(host_s)
        log.update({k: float(np.mean(v)) for k, v in losses.items()})
        return state, log

    # ------------------------------------------------------------- evaluation
    def evaluate(
        self,
        state: TrainState,
        tasks: TaskParams | None = None,
        online: bool = False,
        key: Array | None = None,
    ) -> dict:
        """method §8 metrics on `tasks` (default: test tasks), mean and per seed, of the deployed
        policy and encoder parameters (`acting_params`)."""
        tasks = self.test_tasks if tasks is None else tasks
        key = jax.random.PRNGKey(EVAL_SEED) if key is None else key
        fn = self.evaluate_online if online else self.evaluate_adapt
        learner = state.learner
        params = acting_params(learner.params)
        result = to_host(fn(key, params, tasks))
        return eval_lib.summarize(result, tasks, self.env.config.robot_radius) | {"_raw": result}

    def steps_per_iteration(self) -> int:
        tc = self.cfg.train
        per = tc.tasks_per_iteration * (tc.prior_episodes + tc.posterior_episodes)
        return per * self.horizon
