"""MPC-PEARL meta-training (Algorithm 1) for many seeds in one program.

`Trainer(cfg)` builds the env, tasks, networks, MPC bridge and three jitted phases:
  * collection (a `Phase`: the initial, prior-z and posterior-z collections of Algorithm 1)
    over a flat batch of seeds x tasks x episodes (`mpcpearl_jax.collection`), with
    event-triggered MPC: the host solver through one `pure_callback` per step where an event
    fires (`mpc.bridge`);
  * the N_train gradient steps as one `lax.scan` (run in chunks), vmapped over seeds, buffers
    donated;
  * meta-test evaluation (Algorithm 2), vmapped over seeds and tasks.
`Trainer.iteration` reads as Algorithm 1, lines 3-23.
With several devices (`cfg.devices`, `mpcpearl_jax.distributed`) the seed axis of every phase is
split over a device mesh; each seed computes what it computes on one device.
The whole `TrainState` (params, optimizer states, target nets, buffers, RNG keys, iteration) is a
pytree, checkpointed by `mpcpearl_jax.training.checkpoint`.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import Array

from mpcpearl_jax import collection as collect_lib
from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.distributed import constrain, first_local, make_mesh, sum_over_processes, to_host
from mpcpearl_jax.envs import make_env, redraw_tasks, tasks_for
from mpcpearl_jax.envs.perturb import delay_people
from mpcpearl_jax.envs.types import TaskParams
from mpcpearl_jax.errors import ConfigError, TrainingDiverged
from mpcpearl_jax.evaluation import evaluate as eval_lib
from mpcpearl_jax.evaluation.evaluate import EVAL_SEED
from mpcpearl_jax.pearl import buffers
from mpcpearl_jax.pearl.learner import (
    LearnerState,
    acting_params,
    init_learner,
    make_update,
)
from mpcpearl_jax.pearl.networks import Networks
from mpcpearl_jax.pearl.types import context_from
from mpcpearl_jax.training.protocol import split_keys


class IterationAbandoned(Exception):
    """`iteration(state, stop)` stopped early because stop() became true; the state passed in
    was consumed (its buffers donated) and must not be used: restore a checkpoint."""


def _poll(state: TrainState, stop: Callable[[], bool] | None) -> None:
    """Between two collection phases: once the phase dispatched last has run, raise
    IterationAbandoned if stop() is true (a stop in the first iteration then waits for one phase
    at most, not for the whole collection)."""
    if stop is not None:
        jax.block_until_ready(state.rl.size)
        if stop():
            raise IterationAbandoned


# gradient steps per jitted update call: the update phase runs in chunks of this many steps (the
# same keys and results as one scan), so a stop request is answered between chunks (~7 s at the
# paper's sizes on a 2-core CPU)
UPDATE_CHUNK = 25


@dataclasses.dataclass(frozen=True)
class Phase:
    """One collection phase of Algorithm 1 on each visited task: `episodes` episodes with z from
    the prior N(0, I) or, `posterior`, from q_phi(z | c) with c sampled from the task's encoder
    buffer; every transition goes to the task's replay buffer H^i (line 15) and, `to_encoder`,
    to its encoder buffer too, which `clear_encoder` empties first (line 5: c^i = {})."""

    episodes: int
    posterior: bool
    to_encoder: bool
    clear_encoder: bool


def prior_phase(episodes: int) -> Phase:
    """Algorithm 1 line 5 then lines 6-15: c^i = {}, z^i ~ N(0, I); the episodes refill the
    encoder buffer, the context of the posterior phase and of training."""
    return Phase(episodes, posterior=False, to_encoder=True, clear_encoder=True)


def posterior_phase(episodes: int) -> Phase:
    """Algorithm 1 lines 16-17 then lines 6-15: c^i from the encoder buffer, z^i ~ q_phi(z |
    c^i); the episodes go to H^i only (and may start elsewhere: `explore_start_share`)."""
    return Phase(episodes, posterior=True, to_encoder=False, clear_encoder=False)


class TrainState(struct.PyTreeNode):
    """Everything that evolves during training; every leaf has a leading seed axis [S]."""

    learner: LearnerState
    rl: buffers.TaskBuffer
    enc: buffers.TaskBuffer
    tasks: TaskParams  # [S, N, ...] training tasks as collected (redraw_behaviours changes them)
    key: Array  # [S, 2] PRNG keys
    iteration: Array  # [S] int32 completed iterations (0 = only the initial collection pending)


def _set_tasks(tasks: TaskParams, ids: Array, new: TaskParams) -> TaskParams:
    """tasks [S, N, ...] with the rows ids [S, k] replaced by new [S, k, ...]."""
    seed_ix = jnp.arange(ids.shape[0])[:, None]
    return jax.tree_util.tree_map(
        lambda x, y: x.at[seed_ix, ids].set(y.astype(x.dtype)), tasks, new
    )


def _episode_stats(ep: collect_lib.Episodes, explore: Array | None) -> dict:
    """Per-seed statistics [S] of episodes [S, R, T]: return, success and collision-free rate
    over the rows the policy drives from the task's start (every row without exploring
    starts), event and MPC shares over every step, the exploring rows' share and success
    apart."""
    success = jnp.any(ep.in_goal, -1) & ~jnp.any(ep.collision, -1)  # [S, R]
    x_rows = jnp.zeros(success.shape) if explore is None else explore.astype(jnp.float32)
    mean_over = lambda w, x: jnp.sum(w * x, -1) / jnp.maximum(jnp.sum(w, -1), 1.0)  # noqa: E731
    on_start = lambda x: mean_over(1.0 - x_rows, x)  # noqa: E731
    stats = {
        "return": on_start(jnp.sum(ep.transitions.reward, axis=-1)),
        "success": on_start(success),
        "collision_free": on_start(~jnp.any(ep.collision, -1)),
        "event_rate": jnp.mean(ep.event, axis=(-1, -2)),
        "mpc_share": jnp.mean(ep.used_mpc, axis=(-1, -2)),
        "explore_rows": jnp.mean(x_rows, axis=-1),
        "explore_success": mean_over(x_rows, success),
        "steps": jnp.asarray(ep.transitions.reward[0].size),
    }
    return stats


# the episode statistics the training log reports as train_<name>
_TRAIN_STATS = (
    "return",
    "success",
    "collision_free",
    "event_rate",
    "mpc_share",
    "explore_rows",
    "explore_success",
)


def _collection_log(prior: dict, post: dict | None) -> dict:
    """The log's episode statistics, means over seeds: `train_<name>` of the posterior phase
    (of the prior phase without one) and `train_prior_return`."""
    src = post if post is not None else prior
    names = [n for n in _TRAIN_STATS if n in src]
    src, prior_ret = to_host(({n: src[n] for n in names}, prior["return"]))
    log = {f"train_{n}": float(np.mean(src[n])) for n in names}
    log["train_prior_return"] = float(np.mean(prior_ret))
    return log


def _check_finite(losses: dict, iteration: int) -> None:
    bad = [k for k, v in losses.items() if not np.all(np.isfinite(v))]
    if bad:
        raise TrainingDiverged(
            f"non-finite losses {bad} at iteration {iteration}; "
            "the last good checkpoint is kept (lower the learning rate or reward scale)"
        )


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
        self.mesh = make_mesh(cfg.seeds, cfg.devices)  # None: one device, no sharding
        self.obs_dim = self.env.obs_dim(self.train_tasks)
        self.action_dim = self.env.action_dim
        self.nets = Networks(
            cfg.pearl, self.obs_dim, self.action_dim, self.env.obs_layout(self.train_tasks)
        )
        self.horizon = self.env.config.horizon
        tc = cfg.train
        self.enc_capacity = tc.prior_episodes * self.horizon
        self.bridge = None
        if tc.uses_mpc:
            from mpcpearl_jax.mpc import make_mpc_bridge

            self.bridge = make_mpc_bridge(self.env, cfg.mpc)
        self.imitates = cfg.pearl.imitation > 0
        self._collector = collect_lib.make_collector(
            self.env, self.nets, self.bridge, tc.eps, mesh=self.mesh, mark_expert=self.imitates
        )
        self._update_body = make_update(self.nets, jit=False)
        self.collect_phase = jax.jit(self._collect_phase, static_argnums=2, donate_argnums=0)
        # the pipelined iteration (`train.pipeline`): collection beside the updates reads the
        # buffers the updates read, so it gathers without donating and stores after them
        self._gather_jit = jax.jit(self._gather, static_argnums=5)
        self._store_jit = jax.jit(self._store, donate_argnums=0)
        self._copy_jit = jax.jit(lambda tree: jax.tree_util.tree_map(jnp.copy, tree))
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
        keys, sub = split_keys(keys, 1)
        learner = jax.vmap(lambda k: init_learner(k, self.nets))(sub[:, 0])
        # phases donate their input state: give the learner's aliased leaves (target V = V at
        # init) their own buffers; the replay buffers are created unaliased and at full size once
        learner = jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), learner)
        n, od, ad, lead = self.num_train, self.obs_dim, self.action_dim, (cfg.seeds,)
        mark = self.imitates  # the buffers keep the MPC's mark (`pearl.imitation`)
        rl = buffers.init_buffer(n, cfg.train.rl_capacity, od, ad, lead, expert=mark)
        enc = buffers.init_buffer(n, self.enc_capacity, od, ad, lead, expert=mark)
        tasks = jax.tree_util.tree_map(
            lambda x: jnp.array(jnp.broadcast_to(x, (cfg.seeds, *x.shape))), self.train_tasks
        )
        iteration = jnp.zeros((cfg.seeds,), jnp.int32)
        state = TrainState(learner, rl, enc, tasks, keys, iteration)
        return constrain(state, self.mesh)

    # ------------------------------------------------------------- collection
    def initial_collection(self, state: TrainState) -> tuple[TrainState, dict]:
        """Before the first iteration, as in the authors' code: `initial_episodes` prior-phase
        episodes on every training task, so each H^i holds data before training (Algorithm 1,
        line 2 initialises the buffers)."""
        ids = jnp.broadcast_to(jnp.arange(self.num_train), (self.cfg.seeds, self.num_train))
        return self.collect_phase(state, ids, prior_phase(self.cfg.train.initial_episodes))

    def prior_collection(self, state: TrainState, ids: Array) -> tuple[TrainState, dict]:
        """Algorithm 1 lines 5-15 on the tasks ids [S, k]: c^i = {} and z^i ~ N(0, I), then
        `prior_episodes` episodes into H^i and the encoder buffer (the context)."""
        return self.collect_phase(state, ids, prior_phase(self.cfg.train.prior_episodes))

    def posterior_collection(self, state: TrainState, ids: Array) -> tuple[TrainState, dict]:
        """Algorithm 1 lines 16-17, then 6-15 again, on the tasks ids [S, k]: c^i sampled from
        the encoder buffer, z^i ~ q_phi(z | c^i), `posterior_episodes` episodes into H^i only."""
        return self.collect_phase(state, ids, posterior_phase(self.cfg.train.posterior_episodes))

    def _row_z(self, encoder, enc, keys: Array, rows: Array, posterior: bool) -> Array:
        """z [S, R, L] per collection row: prior samples, or posterior of sampled context
        (encoder: the encoder's parameters [S], enc: the encoder buffers [S])."""
        cfg = self.cfg.pearl

        def per_seed(encoder, enc, key, rows_s):
            k_c, k_z = jax.random.split(key)
            if not posterior:
                return self.nets.prior_z(k_z, rows_s.shape[:1])
            ctx = context_from(buffers.sample(enc, k_c, rows_s, cfg.context_size))
            return self.nets.sample_z(encoder, ctx, k_z)

        return jax.vmap(per_seed)(encoder, enc, keys, rows)

    def _collect_phase(
        self, state: TrainState, task_ids: Array, phase: Phase
    ) -> tuple[TrainState, dict]:
        """Collect `phase.episodes` per task of task_ids [S, k] (`collection`, event-triggered MPC
        included) and store them. Returns (state, stats [S])."""
        enc, key, per_task, stats = self._gather(
            state.learner.params, state.enc, state.tasks, state.key, task_ids, phase
        )
        rl = jax.vmap(buffers.insert)(state.rl, task_ids, per_task)
        new = state.replace(rl=rl, enc=enc, key=key)
        return constrain(new, self.mesh), stats

    def _gather(
        self, params, enc, tasks: TaskParams, key: Array, task_ids: Array, phase: Phase
    ) -> tuple[Any, Array, Any, dict]:
        """The episodes of one phase on the tasks task_ids [S, k], acted by `params` (the policy
        and encoder, [S]), with the encoder buffers `enc` cleared and refilled as the phase says:
        -> (enc, the carried keys [S, 2], the transitions per task [S, k, E * T, ...] for the
        replay buffers, stats [S])."""
        keys, sub = split_keys(key, 2)
        rows = jnp.repeat(task_ids, phase.episodes, axis=1)  # [S, k * E]
        if phase.clear_encoder:
            enc = jax.vmap(buffers.clear)(enc, task_ids)
        z = self._row_z(params["encoder"], enc, sub[:, 0], rows, phase.posterior)
        row_tasks = jax.vmap(collect_lib.rows_of)(tasks, rows)
        share = self.cfg.train.explore_start_share
        explore = None
        if share > 0 and phase.posterior and not phase.to_encoder:  # extension: exploring starts
            k_explore = jax.random.fold_in(sub[0, 1], 11)
            explore = jax.random.uniform(k_explore, rows.shape) < share
        ep = self._collector(sub[0, 1], params["policy"], z, row_tasks, explore)
        s, k = task_ids.shape
        to_task = lambda x: x.reshape((s, k, phase.episodes * self.horizon, *x.shape[3:]))  # noqa: E731
        per_task = jax.tree_util.tree_map(to_task, ep.transitions)
        if phase.to_encoder:
            enc = jax.vmap(buffers.insert)(enc, task_ids, per_task)
        enc, keys, per_task = constrain((enc, keys, per_task), self.mesh)
        return enc, keys, per_task, _episode_stats(ep, explore)

    # ------------------------------------------------------ tasks of a visit
    def _choose_tasks(self, state: TrainState, k: int) -> tuple[TrainState, Array]:
        """k training tasks per seed, drawn without replacement: ids [S, k]."""
        keys, sub = split_keys(state.key, 1)
        n = self.num_train
        pick = lambda key: jax.random.choice(key, n, (min(k, n),), replace=False)
        return state.replace(key=keys), jax.vmap(pick)(sub[:, 0])

    def _visit_tasks(self, state: TrainState, ids: Array, iteration: int) -> TrainState:
        """The extensions that change a training task each time it is visited, before its
        episodes (after the initial collection; docs/extensions.md): its people get a fresh
        behaviour (`redraw_behaviours`), then a fresh delay per person (`crowd_delay_max`)."""
        tc = self.cfg.train
        if tc.redraw_behaviours:
            state = self._redraw(state, ids, iteration)
        if tc.crowd_delay_max > 0:
            state = self._delay_crowds(state, ids)
        return state

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
        return state.replace(tasks=_set_tasks(state.tasks, ids, new))

    def _delay_crowds(self, state: TrainState, ids: Array) -> TrainState:
        """Extension `crowd_delay_max`: the visited tasks ids [S, k] get their people's paths
        with a fresh random delay per person (`envs.perturb.delay_people`), applied to the
        task's own crowd (the one just re-drawn with `redraw_behaviours`, else the original
        training task), so delays never accumulate over visits. Keys come from the run's stream
        in `TrainState`, so a resumed run draws the same delays."""
        return self._delay_crowds_jit(state, ids)

    def _delay_crowds_impl(self, state: TrainState, ids: Array) -> TrainState:
        keys, sub = split_keys(state.key, 1)
        if self.cfg.train.redraw_behaviours:  # the crowds just re-drawn
            visited = jax.vmap(collect_lib.rows_of)(state.tasks, ids)  # [S, k, ...]
        else:  # the original training tasks
            visited = collect_lib.rows_of(self.train_tasks, ids)
        people = visited.human_pos.shape[-2]
        top = self.cfg.train.crowd_delay_max
        draw = lambda key: jax.random.randint(key, (ids.shape[1], people), 0, top + 1)  # noqa: E731
        delays = jax.vmap(draw)(sub[:, 0])  # [S, k, H]
        new = jax.vmap(delay_people)(visited, delays)
        tasks = _set_tasks(state.tasks, ids, new)
        return constrain(state.replace(tasks=tasks, key=keys), self.mesh)

    # ---------------------------------------------------------------- updates
    def update_phase(
        self, state: TrainState, stop: Callable[[], bool] | None = None
    ) -> tuple[TrainState, dict]:
        """The N_train gradient steps (Algorithm 1 lines 18-23) -> (state, mean losses [S]), in
        jitted chunks of `update_chunk` steps over the keys of one scan (the same results);
        raises IterationAbandoned between chunks once stop() is true."""
        keys, step_keys = self._update_keys(state)
        steps = int(step_keys.shape[1])
        learner, parts = state.learner, []
        for lo in range(0, steps, self.update_chunk):
            if stop is not None and stop():
                raise IterationAbandoned
            chunk = step_keys[:, lo : lo + self.update_chunk]
            learner, ms = self._update_steps_jit(learner, state.rl, state.enc, chunk)
            parts.append(jax.block_until_ready(ms))  # a stop request waits one chunk at most
        ms = jax.tree_util.tree_map(lambda *x: jnp.mean(jnp.concatenate(x, axis=1), axis=1), *parts)
        return state.replace(learner=learner, key=keys), ms

    def _update_keys(self, state: TrainState) -> tuple[Array, Array]:
        """(new carry keys [S, 2], one key per gradient step [S, N_train, 2])."""
        keys, sub = split_keys(state.key, 1)
        steps = self.cfg.train.updates_per_iteration
        return keys, jax.vmap(lambda k: jax.random.split(k, steps))(sub[:, 0])

    def _update_steps(self, learner, rl, enc, step_keys: Array) -> tuple[Any, dict]:
        """Gradient steps with keys [S, n, 2] (one scan, vmapped over seeds), each over a
        meta-batch of tasks with a context c^i and a batch B^i (Algorithm 1 line 20) and the
        update of `pearl.learner` (lines 21-23); -> (learner, per-step losses [S, n])."""
        cfg, n = self.cfg.pearl, self.num_train

        def per_seed(learner, rl, enc, keys):
            def body(learner, k):
                k_t, k_b, k_c, k_u = jax.random.split(k, 4)
                tids = jax.random.choice(k_t, n, (cfg.meta_batch,), replace=cfg.meta_batch > n)
                batch = buffers.sample(rl, k_b, tids, cfg.batch_size)
                ctx = context_from(buffers.sample(enc, k_c, tids, cfg.context_size))
                return self._update_body(learner, batch, ctx, k_u)

            return jax.lax.scan(body, learner, keys)

        out = jax.vmap(per_seed)(learner, rl, enc, step_keys)
        return constrain(out, self.mesh)

    # -------------------------------------------------------------- iteration
    def iteration(
        self, state: TrainState, stop: Callable[[], bool] | None = None
    ) -> tuple[TrainState, dict]:
        """One meta-training iteration, Algorithm 1 lines 3-23 (as in the authors' PEARL code), for
        every seed: the data collection (lines 4-17) on `tasks_per_iteration` training tasks drawn
        at random, then the training (lines 18-23). Every step of an episode is acted by the MPC
        when an event fires and rand <= eps (lines 8-11; `collection`), else by pi_theta (line
        13). The extensions (docs/extensions.md) hook in where named: re-drawn or delayed crowds
        per visit, exploring-start rows in the posterior phase. stop (e.g. set by
        Ctrl-C) is polled between the collection phases, before the updates and between update
        chunks; once true the iteration
        is abandoned with IterationAbandoned (the state passed in is consumed). With
        `train.pipeline` the collection runs beside the updates instead, one iteration ahead
        (`_pipelined_iteration`)."""
        if self.cfg.train.pipeline:
            return self._pipelined_iteration(state, stop)
        t0 = time.perf_counter()
        if self.bridge is not None:
            self.bridge.reset_stats()
        it = int(first_local(state.iteration))
        if it == 0:
            state, _ = self.initial_collection(state)
            _poll(state, stop)
        # data collection (lines 4-17)
        state, prior, post = self._collect_visit(state, it + 1, stop)
        jax.block_until_ready(state.rl.size)
        t1 = time.perf_counter()
        # training (lines 18-23): N_train gradient steps
        state, losses = self.update_phase(state, stop)
        losses = to_host(losses)
        t2 = time.perf_counter()
        return self._finish_iteration(state, it, losses, prior, post, t1 - t0, t2 - t1)

    def _collect_visit(
        self, state: TrainState, visit: int, stop: Callable[[], bool] | None = None
    ) -> tuple[TrainState, dict, Any]:
        """Algorithm 1 lines 4-17 for every seed: `tasks_per_iteration` training tasks drawn at
        random, visited (`visit` numbers the visit for the extensions that change a task), their
        prior-phase then posterior-phase episodes stored -> (state, prior stats, posterior stats
        or None); stop is polled after each phase (`_poll`)."""
        state, ids = self._choose_tasks(state, self.cfg.train.tasks_per_iteration)
        state = self._visit_tasks(state, ids, visit)
        state, prior = self.prior_collection(state, ids)  # lines 5-15: z ~ N(0, I)
        post = None
        if self.cfg.train.posterior_episodes > 0:
            _poll(state, stop)
            state, post = self.posterior_collection(state, ids)  # lines 16-17: z ~ q_phi(z | c)
        return state, prior, post

    def _finish_iteration(self, state, it, losses, prior, post, collect_s, update_s):
        _check_finite(losses, it + 1)
        state = state.replace(iteration=state.iteration + 1)
        log: dict[str, Any] = {"iteration": it + 1, "collect_s": collect_s, "update_s": update_s}
        log.update(_collection_log(prior, post))
        log.update(self._mpc_log())
        log.update({k: float(np.mean(v)) for k, v in losses.items()})
        return state, log

    # --------------------------------------------------------- pipelined iteration
    def _pipelined_iteration(
        self, state: TrainState, stop: Callable[[], bool] | None = None
    ) -> tuple[TrainState, dict]:
        """One iteration with `train.pipeline` (docs/usage.md, "Pipelined iterations"): the
        gradient steps of iteration k (lines 18-23) run on the buffers as they are, while a
        second thread collects the episodes of iteration k + 1 (lines 4-17) with the policy and
        encoder from before those steps; the episodes are stored once both are done. The acting
        policy therefore lags one iteration behind Algorithm 1's (the first iteration collects
        its own episodes first, with the initial policy). At the end of an iteration the state
        is whole (the buffers hold the next iteration's episodes), so checkpoints and resume
        are exact as without the pipeline. The log's collection statistics are those of the
        episodes collected during the iteration (for iteration k + 1); `collect_s` and
        `update_s` are the two threads' own times, which overlap."""
        t0 = time.perf_counter()
        if self.bridge is not None:
            self.bridge.reset_stats()
        it = int(first_local(state.iteration))
        if it == 0:  # the first iteration's episodes, acted by the initial policy
            state, _ = self.initial_collection(state)
            _poll(state, stop)
            state, _, _ = self._collect_visit(state, 1, stop)
            _poll(state, stop)
        keys, sub = split_keys(state.key, 1)  # the collection's own key stream
        state = state.replace(key=keys)
        acting = self._copy_jit(
            {"policy": state.learner.params["policy"], "encoder": state.learner.params["encoder"]}
        )
        side = TrainState(None, None, state.enc, state.tasks, sub[:, 0], state.iteration)
        jax.block_until_ready((acting, side))  # the updates donate the learner's buffers
        box: dict[str, Any] = {}

        def collect() -> None:
            try:
                tc = time.perf_counter()
                box["out"] = jax.block_until_ready(self._collect_ahead(side, acting, it + 2))
                box["collect_s"] = time.perf_counter() - tc
            except BaseException as e:  # noqa: BLE001 (re-raised in the training's thread)
                box["error"] = e

        thread = threading.Thread(target=collect, name="pipelined-collection", daemon=True)
        thread.start()
        try:
            t1 = time.perf_counter()
            state, losses = self.update_phase(state, stop)
            losses = to_host(losses)
            update_s = time.perf_counter() - t1
        finally:
            thread.join()
        if "error" in box:
            raise box["error"]
        enc, tasks, ids, per_task, prior, post = box["out"]
        state = state.replace(rl=self._store_jit(state.rl, ids, per_task), enc=enc, tasks=tasks)
        collect_s = box["collect_s"] + (t1 - t0)
        return self._finish_iteration(state, it, losses, prior, post, collect_s, update_s)

    def _collect_ahead(self, side: TrainState, acting, visit: int):
        """The collection of the pipelined iteration on `side` (the encoder buffers, tasks and
        keys; no learner, no replay buffers), acted by `acting` -> (encoder buffers, tasks, task
        ids [S, k], the transitions of each phase per task, prior stats, posterior stats or
        None). Nothing it reads is donated, so the updates may read the same buffers."""
        tc = self.cfg.train
        side, ids = self._choose_tasks(side, tc.tasks_per_iteration)
        side = self._visit_tasks(side, ids, visit)
        enc, key, per_prior, prior = self._gather_jit(
            acting, side.enc, side.tasks, side.key, ids, prior_phase(tc.prior_episodes)
        )
        per_task, post = [per_prior], None
        if tc.posterior_episodes > 0:
            phase = posterior_phase(tc.posterior_episodes)
            enc, key, per_post, post = self._gather_jit(acting, enc, side.tasks, key, ids, phase)
            per_task.append(per_post)
        return enc, side.tasks, ids, tuple(per_task), prior, post

    def _store(self, rl, ids: Array, per_task: tuple) -> Any:
        """The replay buffers with each phase's transitions per task inserted, in order."""
        for part in per_task:
            rl = jax.vmap(buffers.insert)(rl, ids, part)
        return constrain(rl, self.mesh)

    def _mpc_log(self) -> dict:
        """The MPC bridge's counters and times of this iteration, summed over processes (each
        solves its own shards' rows); the fallback reasons are this process's. {} without MPC."""
        if self.bridge is None:
            return {}
        st = self.bridge.stats()
        calls, rows, fallbacks, solve_s, host_s = sum_over_processes(
            [
                st["calls"],
                st["rows_solved"],
                st["fallbacks"],
                float(sum(st["solve_s"])),
                float(sum(st["host_call_s"])),
            ]
        )
        return {
            "mpc_calls": int(calls),
            "mpc_rows": int(rows),
            "mpc_fallbacks": int(fallbacks),
            "mpc_fallback_rate": float(fallbacks) / max(int(rows), 1),
            "mpc_reasons": st["reasons"],
            "mpc_solve_s": float(solve_s),
            "mpc_host_s": float(host_s),
        }

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
        return self.evaluate_episodes(state, tasks, online, key)[0]

    def evaluate_episodes(
        self,
        state: TrainState,
        tasks: TaskParams | None = None,
        online: bool = False,
        key: Array | None = None,
    ) -> tuple[dict, dict]:
        """(`evaluate`'s metrics, the evaluated episodes: arrays [S, N, ...] such as `position`
        and `collision`, for figures)."""
        tasks = self.test_tasks if tasks is None else tasks
        key = jax.random.PRNGKey(EVAL_SEED) if key is None else key
        fn = self.evaluate_online if online else self.evaluate_adapt
        result = to_host(fn(key, acting_params(state.learner.params), tasks))
        return eval_lib.summarize(result, tasks, self.env.config.robot_radius), result

    def steps_per_iteration(self) -> int:
        tc = self.cfg.train
        per = tc.tasks_per_iteration * (tc.prior_episodes + tc.posterior_episodes)
        return per * self.horizon

    def close(self) -> None:
        """Shut the MPC bridge's worker processes down (if any); the trainer's jitted phases
        stay usable, and a later MPC call starts the pool again."""
        if self.bridge is not None:
            self.bridge.close()
