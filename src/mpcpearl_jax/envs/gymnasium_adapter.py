"""The navigation env in Gymnasium's shape: a `gymnasium.Env` and a vmapped `VectorEnv`.

    import gymnasium as gym
    import mpcpearl_jax.envs.gymnasium_adapter  # registers the ids below

    env = gym.make("mpcpearl_jax/Restaurant-v0", render_mode="rgb_array")
    obs, info = env.reset(seed=0)                      # a training task drawn by the seed
    obs, info = env.reset(options={"task": 3})         # or task 3 of the split
    envs = gym.make_vec("mpcpearl_jax/Sidewalk-v0", num_envs=16)  # one jitted call per step

Ids: "mpcpearl_jax/Restaurant-v0" and "mpcpearl_jax/Sidewalk-v0" (registered when this module
is imported; `gym.make("mpcpearl_jax.envs.gymnasium_adapter:mpcpearl_jax/Restaurant-v0")`
imports it for you). Keyword arguments of `gym.make` / `gym.make_vec` reach the constructors:
`split`, `task_seed`, `tasks`, `task`, `env_overrides`, `task_options` (see `GymNavEnv`).

Steps, rewards and events are those of `NavEnv`. The method has no early termination, so
`terminated` is always False and an episode is *truncated* after the family's horizon (80 steps
in the restaurant, 250 on the sidewalk). Observations and actions live in [-1, 1]. The vector
env autoresets (Gymnasium's next-step mode by default, same-step on request) and draws a fresh
task for a slot on each autoreset unless its task was fixed.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

try:  # gymnasium is an optional extra
    import gymnasium
    from gymnasium import spaces
    from gymnasium.vector import AutoresetMode, VectorEnv
    from gymnasium.vector.utils import batch_space
except ImportError as e:
    raise ImportError(
        f'the Gymnasium env needs gymnasium, an optional extra: pip install -e ".[gymnasium]" '
        f"(or pip install gymnasium) ({e})"
    ) from None

from mpcpearl_jax.envs import load_family, make_env, make_tasks
from mpcpearl_jax.envs.navigation import NavEnv
from mpcpearl_jax.envs.types import NavConfig, TaskParams

ENV_IDS = {"restaurant": "mpcpearl_jax/Restaurant-v0", "sidewalk": "mpcpearl_jax/Sidewalk-v0"}
METRIC_NAMES = ("collision", "in_goal", "n_dynamic", "n_static", "event")
FRAME_WIDTH_IN, FRAME_DPI = 5.0, 80  # a 400-pixel-wide frame


# ------------------------------------------------------------------ tasks and compiled programs
def _take(tasks: TaskParams, i: Any) -> TaskParams:
    return jax.tree_util.tree_map(lambda x: x[i], tasks)


@functools.lru_cache(maxsize=16)
def _split_tasks(name: str, split: str, seed: int, config: NavConfig, options: tuple) -> Any:
    return make_tasks(name, split, seed, config=config, **dict(options))


def _build(
    family: str,
    split: str,
    task_seed: int,
    tasks: TaskParams | None,
    env_overrides: Mapping[str, Any] | None,
    task_options: Mapping[str, Any] | None,
) -> tuple[NavEnv, TaskParams]:
    """The family's `NavEnv` and its tasks stacked on a leading axis (a split's tasks are built
    once per process and shared by every env made with the same arguments)."""
    name = load_family(family)
    nav = make_env(name, **dict(env_overrides or {}))
    if tasks is None:
        options = tuple(sorted((task_options or {}).items()))
        try:
            tasks = _split_tasks(name, split, int(task_seed), nav.config, options)
        except TypeError:  # an unhashable task option: build without the cache
            tasks = make_tasks(name, split, int(task_seed), config=nav.config, **dict(options))
    elif tasks.start.ndim == 1:
        tasks = jax.tree_util.tree_map(lambda x: x[None], tasks)
    return nav, tasks


@functools.lru_cache(maxsize=16)
def _programs(config: NavConfig) -> dict[str, Any]:
    """The jitted reset and steps of one family config, compiled once per process."""
    nav = NavEnv(config)

    def reset(key, tasks, task):
        return nav.reset(key, _take(tasks, task))

    def step(key, state, action, tasks, task):
        key, k_step = jax.random.split(key)
        obs, state, reward, done, info = nav.step(k_step, state, action, _take(tasks, task))
        return key, obs, state, reward, done, info

    def v_reset(key, tasks, task):
        keys = jax.random.split(key, task.shape[0])
        return jax.vmap(lambda k, i: nav.reset(k, _take(tasks, i)))(keys, task)

    def v_step(carry, actions, tasks, same_step):
        """One step of every slot with autoreset; `same_step` (static) picks the mode. Returns
        the new carry, the observations (after any reset), rewards, whether each slot's
        episode ended, whether each slot stepped (not reset), the stepped observations and the
        step's metrics."""
        state, task, key = carry["state"], carry["task"], carry["key"]
        n = task.shape[0]
        key, k_step, k_task, k_reset = jax.random.split(key, 4)
        obs, nstate, reward, done, info = jax.vmap(
            lambda k, s, a, i: nav.step(k, s, a, _take(tasks, i))
        )(jax.random.split(k_step, n), state, actions, task)
        # the slots that reset now: next-step mode those that ended on the last call, same-step
        # mode those that end on this one; each draws a new task unless its task is fixed
        if same_step:
            resets, stepped = done, jnp.ones_like(done)
        else:  # a resetting slot ignores its action: reward 0, not done
            resets, stepped = carry["pending"], ~carry["pending"]
            reward, done = jnp.where(stepped, reward, 0.0), done & stepped
        drawn = jax.random.randint(k_task, (n,), 0, tasks.start.shape[0])
        new_task = jnp.where(resets & carry["draw"], drawn, task)
        r_obs, r_state = v_reset(k_reset, tasks, new_task)

        def pick(a, b):  # a where the slot resets, else b
            return jnp.where(resets.reshape((n,) + (1,) * (a.ndim - 1)), a, b)

        carry = dict(
            state=jax.tree_util.tree_map(pick, r_state, nstate),
            task=new_task,
            key=key,
            pending=done,
            draw=carry["draw"],
        )
        metrics = {m: getattr(info, m) for m in METRIC_NAMES}
        return carry, pick(r_obs, obs), reward, done, stepped, obs, metrics

    return dict(
        reset=jax.jit(reset),
        step=jax.jit(step),
        v_reset=jax.jit(v_reset),
        v_step=jax.jit(v_step, static_argnames="same_step"),
    )


def _spaces(nav: NavEnv, tasks: TaskParams) -> tuple[spaces.Box, spaces.Box]:
    obs = spaces.Box(-1.0, 1.0, (nav.obs_dim(tasks),), np.float32)
    return obs, spaces.Box(-1.0, 1.0, (nav.action_dim,), np.float32)


def _raw_key(rng: np.random.Generator) -> np.ndarray:
    """A JAX PRNG key (raw uint32 [2]) drawn from the env's NumPy generator."""
    return rng.integers(0, 2**32, size=2, dtype=np.uint32)


def _task_index(task: Any, num_tasks: int) -> int:
    i = int(task)
    if i != task or not 0 <= i < num_tasks:
        raise ValueError(f"task must be an index in [0, {num_tasks}), got {task!r}")
    return i


def _metric(name: str, value: Any) -> Any:
    return float(value) if name in ("n_dynamic", "n_static") else bool(value)


# ------------------------------------------------------------------------------------ frames
def render_frame(
    task: TaskParams,
    config: NavConfig,
    positions: Any,
    collisions: Any = None,
    heading: float | None = None,
    t: int | None = None,
) -> np.ndarray:
    """One frame [height, width, 3] uint8 of an episode so far, drawn by `envs.drawing`: the
    task's arena, obstacles, people's paths, start and goal, the robot's path (positions
    [t + 1, 2], collisions [t] starred), and the people and the robot at step t (default: the
    last position) as discs of their radius."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    from mpcpearl_jax.envs import drawing

    pos = np.asarray(positions, dtype=float).reshape(-1, 2)
    t = len(pos) - 1 if t is None else t
    hits = None if collisions is None else {"robot": np.asarray(collisions, bool)}
    lo, hi = np.asarray(config.arena_lo), np.asarray(config.arena_hi)
    aspect = (hi[1] - lo[1]) / (hi[0] - lo[0])
    fig = Figure(figsize=(FRAME_WIDTH_IN, FRAME_WIDTH_IN * aspect), dpi=FRAME_DPI)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.02, 0.02, 0.96, 0.91))  # room for the step line above
    drawing.plot_episode(task, {"robot": pos}, hits, config, ax=ax)
    humans, mask = np.asarray(task.human_pos), np.asarray(task.human_mask, bool)
    step = min(t, humans.shape[0] - 1)
    for h in np.flatnonzero(mask[step]):
        ax.add_patch(Circle(humans[step, h], config.human_radius, color=drawing.HUMAN_COLOR))
    ax.add_patch(Circle(pos[-1], config.robot_radius, facecolor="0.6", edgecolor="k", zorder=6))
    if heading is not None:
        tip = pos[-1] + 1.5 * config.robot_radius * np.array([np.cos(heading), np.sin(heading)])
        ax.plot([pos[-1, 0], tip[0]], [pos[-1, 1], tip[1]], "-", color="k", lw=1.6, zorder=7)
    ax.set_title(f"step {t}/{config.horizon}", fontsize=8)
    ax.set_axis_off()
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


# ------------------------------------------------------------------------------- single env
class GymNavEnv(gymnasium.Env):
    """One navigation env of a task family as a `gymnasium.Env`.

    Args:
      family: a registered family ("restaurant", "sidewalk") or MODULE:NAME of your own.
      split: the task split reset draws from ("train", "test", "ood", "val").
      task_seed: the seed of the task set (as `make_tasks`).
      tasks: your own tasks (single or stacked `TaskParams`) instead of a split.
      task: fix every episode to this task index (default: a task drawn on each reset; a reset
        with `options={"task": i}` fixes that episode's task).
      render_mode: None or "rgb_array" (the frames of `render_frame`).
      env_overrides: `NavConfig` fields to replace (as `make_env`'s keyword overrides).
      task_options: keyword options of the family's task builder (e.g. `data=` for the
        sidewalk's trajectory file).

    `info` holds the task index, the step `t` and, after a step, `collision`, `in_goal`,
    `n_dynamic`, `n_static` and `event` (the MPC trigger at the pre-step state).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        family: str = "restaurant",
        split: str = "train",
        task_seed: int = 0,
        *,
        tasks: TaskParams | None = None,
        task: int | None = None,
        render_mode: str | None = None,
        env_overrides: Mapping[str, Any] | None = None,
        task_options: Mapping[str, Any] | None = None,
    ):
        self.nav, self.tasks = _build(family, split, task_seed, tasks, env_overrides, task_options)
        self.num_tasks = int(self.tasks.start.shape[0])
        self.fixed_task = None if task is None else _task_index(task, self.num_tasks)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.nav.config.dt)}
        self.observation_space, self.action_space = _spaces(self.nav, self.tasks)
        self._programs = _programs(self.nav.config)
        self._state: Any = None
        self._task = 0
        self._key: Any = None
        self._trail: list[np.ndarray] = []
        self._hits: list[bool] = []

    @property
    def horizon(self) -> int:
        """Steps per episode; the step that reaches it is truncated."""
        return self.nav.config.horizon

    @property
    def task(self) -> int:
        """The index of the current episode's task."""
        return self._task

    def task_params(self, task: int | None = None) -> TaskParams:
        """The params of task index `task` (default: the current episode's)."""
        return _take(self.tasks, self._task if task is None else task)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode: task `options["task"]`, else the fixed task, else one drawn from
        the split with the env's generator (seeded by `seed`)."""
        super().reset(seed=seed)
        options = options or {}
        if options.get("task") is not None:
            self._task = _task_index(options["task"], self.num_tasks)
        elif self.fixed_task is not None:
            self._task = self.fixed_task
        else:
            self._task = int(self.np_random.integers(self.num_tasks))
        self._key = _raw_key(self.np_random)
        obs, self._state = self._programs["reset"](self._key, self.tasks, self._task)
        obs, pose = jax.device_get((obs, self._state.pose))
        self._trail, self._hits = [np.asarray(pose)], []
        return np.array(obs), {"task": self._task, "t": 0}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset before step")
        a = np.asarray(action, dtype=np.float32)
        if a.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {a.shape}")
        self._key, obs, self._state, reward, done, info = self._programs["step"](
            self._key, self._state, a, self.tasks, self._task
        )
        obs, reward, done, info, pose, t = jax.device_get(
            (obs, reward, done, info, self._state.pose, self._state.t)
        )
        out: dict[str, Any] = {"task": self._task, "t": int(t)}
        out.update({m: _metric(m, getattr(info, m)) for m in METRIC_NAMES})
        self._trail.append(np.asarray(pose))
        self._hits.append(bool(out["collision"]))
        return np.array(obs), float(reward), False, bool(done), out

    def render(self) -> np.ndarray | None:
        """The current frame (`render_frame`) with render_mode "rgb_array"; else None."""
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() without a render_mode: make the env with render_mode='rgb_array'"
            )
            return None
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset before render")
        trail = np.stack(self._trail)
        return render_frame(
            self.task_params(), self.nav.config, trail[:, :2], self._hits, float(trail[-1, 2])
        )


# ------------------------------------------------------------------------------- vector env
class GymNavVectorEnv(VectorEnv):
    """`num_envs` navigation envs stepped together in one jitted, vmapped call.

    Arguments as `GymNavEnv`; `task` may also be a sequence of `num_envs` indices, and a reset
    with `options={"task": ...}` (an index or one per slot) fixes the slots' tasks until the
    next reset without it. `autoreset_mode`: Gymnasium's `AutoresetMode.NEXT_STEP` (default:
    the call after an episode ends resets that slot, with reward 0 and its action ignored) or
    `SAME_STEP` (the slot resets on the step that ends it; the last observation is in
    `info["final_obs"]`, its metrics in `info["final_info"]`), or their values "NextStep" and
    "SameStep". Each autoreset draws a new task for a slot unless its task is fixed.
    """

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 8,
        family: str = "restaurant",
        split: str = "train",
        task_seed: int = 0,
        *,
        tasks: TaskParams | None = None,
        task: int | Sequence[int] | None = None,
        render_mode: str | None = None,
        env_overrides: Mapping[str, Any] | None = None,
        task_options: Mapping[str, Any] | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    ):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        self.num_envs = int(num_envs)
        self.nav, self.tasks = _build(family, split, task_seed, tasks, env_overrides, task_options)
        self.num_tasks = int(self.tasks.start.shape[0])
        self.fixed_task = None if task is None else self._slots(task)
        mode = AutoresetMode(autoreset_mode)
        if mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
            raise ValueError(f"autoreset_mode must be NextStep or SameStep, got {mode.value}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.metadata = {
            **self.metadata,
            "autoreset_mode": mode,
            "render_fps": round(1.0 / self.nav.config.dt),
        }
        single_obs, single_action = _spaces(self.nav, self.tasks)
        self.single_observation_space, self.single_action_space = single_obs, single_action
        self.observation_space = batch_space(single_obs, self.num_envs)
        self.action_space = batch_space(single_action, self.num_envs)
        self._programs = _programs(self.nav.config)
        self._carry: dict[str, Any] | None = None
        self._trails: list[list[np.ndarray]] = []
        self._hits: list[list[bool]] = []

    @property
    def horizon(self) -> int:
        return self.nav.config.horizon

    @property
    def task(self) -> np.ndarray:
        """The task index of each slot's current episode [num_envs]."""
        if self._carry is None:
            raise gymnasium.error.ResetNeeded("call reset first")
        return np.asarray(self._carry["task"])

    def _slots(self, task: int | Sequence[int]) -> np.ndarray:
        idx = np.broadcast_to(np.asarray(task), (self.num_envs,))
        return np.array([_task_index(i, self.num_tasks) for i in idx], np.int32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        options = options or {}
        if options.get("task") is not None:
            task, draw = self._slots(options["task"]), False
        elif self.fixed_task is not None:
            task, draw = self.fixed_task, False
        else:
            task = self.np_random.integers(0, self.num_tasks, self.num_envs).astype(np.int32)
            draw = True
        key = _raw_key(self.np_random)
        k_reset, key = jax.random.split(jnp.asarray(key))
        obs, state = self._programs["v_reset"](k_reset, self.tasks, jnp.asarray(task))
        self._carry = dict(
            state=state,
            task=jnp.asarray(task),
            key=key,
            pending=jnp.zeros(self.num_envs, bool),
            draw=jnp.full(self.num_envs, draw),
        )
        obs = np.array(obs)
        if self.render_mode is not None:
            pose = np.asarray(state.pose)
            self._trails = [[p] for p in pose]
            self._hits = [[] for _ in range(self.num_envs)]
        mask = np.ones(self.num_envs, bool)
        return obs, {
            "task": task.copy(),
            "_task": mask,
            "t": np.zeros(self.num_envs, np.int32),
            "_t": mask.copy(),
        }

    def step(
        self, actions: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if self._carry is None:
            raise gymnasium.error.ResetNeeded("call reset before step")
        a = np.asarray(actions, dtype=np.float32)
        if a.shape != self.action_space.shape:
            raise ValueError(f"actions must have shape {self.action_space.shape}, got {a.shape}")
        same_step = self.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
        pending = self._carry["pending"]
        self._carry, obs, reward, done, stepped, final_obs, metrics = self._programs["v_step"](
            self._carry, a, self.tasks, same_step=same_step
        )
        obs, reward, done, stepped, final_obs, metrics, task, t, pose, pending = jax.device_get(
            (
                obs,
                reward,
                done,
                stepped,
                final_obs,
                metrics,
                self._carry["task"],
                self._carry["state"].t,
                self._carry["state"].pose,
                pending,
            )
        )
        done, stepped = np.asarray(done, bool), np.asarray(stepped, bool)
        info: dict[str, Any] = {}
        for m in METRIC_NAMES:
            dtype = np.float64 if m in ("n_dynamic", "n_static") else np.bool_
            info[m] = np.where(stepped, metrics[m], 0).astype(dtype)
            info[f"_{m}"] = stepped.copy()
        info["task"], info["_task"] = np.array(task), np.ones(self.num_envs, bool)
        info["t"], info["_t"] = np.array(t), np.ones(self.num_envs, bool)
        if same_step and done.any():
            finals = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(done):
                finals[i] = np.array(final_obs[i])
            info["final_obs"], info["_final_obs"] = finals, done.copy()
            info["final_info"] = {k: info[k].copy() for k in METRIC_NAMES}
            info["final_info"].update({f"_{k}": done.copy() for k in METRIC_NAMES})
            info["_final_info"] = done.copy()
        if self.render_mode is not None:
            self._record(np.asarray(pose), info["collision"], done, pending, same_step)
        truncated = done.copy()
        return np.array(obs), np.asarray(reward, np.float64), np.zeros_like(done), truncated, info

    def _record(self, pose, hits, done, pending, same_step) -> None:
        for i in range(self.num_envs):
            if (same_step and done[i]) or (not same_step and pending[i]):
                self._trails[i], self._hits[i] = [pose[i]], []
            else:
                self._trails[i].append(pose[i])
                self._hits[i].append(bool(hits[i]))

    def render(self) -> tuple[np.ndarray, ...] | None:
        """Each slot's current frame (`render_frame`) with render_mode "rgb_array"."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() without a render_mode")
            return None
        if self._carry is None:
            raise gymnasium.error.ResetNeeded("call reset before render")
        task = np.asarray(self._carry["task"])
        frames = []
        for i in range(self.num_envs):
            trail = np.stack(self._trails[i])
            params = _take(self.tasks, int(task[i]))
            frames.append(
                render_frame(
                    params, self.nav.config, trail[:, :2], self._hits[i], float(trail[-1, 2])
                )
            )
        return tuple(frames)


def _register() -> None:
    """The ids of the built-in families (idempotent)."""
    for family, env_id in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point=f"{__name__}:GymNavEnv",
                vector_entry_point=f"{__name__}:GymNavVectorEnv",
                kwargs={"family": family},
            )


_register()
