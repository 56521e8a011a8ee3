"""A trained policy in a control loop of your own: observations and the reward of eq. (2) from raw
sensor arrays, and online adaptation from the transitions just lived (method §7).

A robot knows its pose, the people it currently sees, the static obstacles and its goal; it has
no `TaskParams` or `EnvState`. Here those arrays go in directly:

    policy = load_policy(run_dir)                # or load_exported(run_dir / "policy.export")
    adapter = Adapter(policy)                    # the run's observation options and t_update
    state = adapter.init(Scene.circles(goal, table_centres, table_radius), key)
    frame = Frame.start(pose, people, present)   # step 0
    while running:
        action = adapter.act(state, frame)       # [2] in [-1, 1]^2; adapter.command -> (v, delta)
        ...                                      # drive, then sense again
        next_frame = frame.advance(pose, people, present)
        state = adapter.add(state, frame, action, next_frame)   # reward, context row, z
        frame = next_frame

`observe(layout, frame, scene)` builds exactly the observation the run was trained on (its env
options: velocities, sensing range, egocentric and sorted entries, clock) and `reward(...)` the
reward of eq. (2) as the env pays it; both are pure and jittable. `Adapter` keeps the context rows
(s, a, r, s') in the layout `infer_z` expects and re-infers z every `t_update` transitions, the
paper's online adaptation protocol, reproducing `evaluate.make_evaluator(online=True)`.

Coordinates are metres and radians in the frame of the arena the policy was trained in
(`layout.config.arena_lo`, `arena_hi`); a robot maps its map frame onto it.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from mpcpearl_jax.deploy.exported import check_key
from mpcpearl_jax.envs import physics
from mpcpearl_jax.envs.dynamics import bicycle_step, to_physical
from mpcpearl_jax.envs.observation import layout as observation_layout
from mpcpearl_jax.envs.observation import obs_dim as observation_dim
from mpcpearl_jax.envs.observation import observation
from mpcpearl_jax.envs.types import NavConfig, TaskParams


# ------------------------------------------------------------------------------ inputs
class Scene(NamedTuple):
    """What stays fixed through an episode: the goal and the static obstacles, as rounded boxes
    (the points within `static_radius` of the box [static_lo, static_hi]; a round table is a box
    with lo == hi)."""

    goal: Array  # [2]
    static_lo: Array  # [S, 2]
    static_hi: Array  # [S, 2]
    static_radius: Array  # [S]

    @classmethod
    def circles(cls, goal: Any, centres: Any, radius: Any) -> Scene:
        """Round obstacles (e.g. tables): centres [S, 2], radius [S] or one for all."""
        c = _points("centres", centres)
        r = _radii(radius, c)
        return cls(jnp.asarray(goal, jnp.float32), c, c, r)

    @classmethod
    def boxes(cls, goal: Any, lo: Any, hi: Any, radius: Any = 0.0) -> Scene:
        """Axis-aligned boxes (e.g. walls, parked cars): corners lo, hi [S, 2]; radius [S] or
        one for all (0: sharp corners)."""
        lo, hi = _points("lo", lo), _points("hi", hi)
        if lo.shape != hi.shape:
            raise ValueError(f"hi: expected shape {list(lo.shape)} (as lo), got {list(hi.shape)}")
        return cls(jnp.asarray(goal, jnp.float32), lo, hi, _radii(radius, lo))

    @classmethod
    def from_task(cls, task: TaskParams) -> Scene:
        """The scene of one of the project's tasks (a single task, not a stack)."""
        return cls(task.goal, task.static_lo, task.static_hi, task.static_radius)


class Frame(NamedTuple):
    """What the robot senses at step t of an episode. Row i of `people` and `prev_people` is
    the same person (a tracker's identity); `present` marks the rows that hold somebody now,
    `prev_present` those that did a step earlier. Absent rows may hold anything (NaN too)."""

    pose: Array  # [3] x, y (m), heading (rad)
    people: Array  # [N, 2] positions (m) at step t
    present: Array  # [N] bool
    prev_people: Array  # [N, 2] the same people at step t - 1 (at t = 0: `people`)
    prev_present: Array  # [N] bool
    t: Array  # [] int, steps since the episode began

    @classmethod
    def start(cls, pose: Any, people: Any, present: Any = None) -> Frame:
        """The first frame of an episode (t = 0, the people not moving yet). present: default
        everybody."""
        people = _people(people)
        present = _presence(present, people)
        t = jnp.zeros((), jnp.int32)
        return cls(jnp.asarray(pose, jnp.float32), people, present, people, present, t)

    def advance(self, pose: Any, people: Any, present: Any = None) -> Frame:
        """The next frame (t + 1): what was sensed now becomes the previous step's people. Keep
        the rows fixed (one per track id, `present` False for those not seen now)."""
        people = _people(people)
        if people.shape[0] != self.people.shape[0]:
            raise ValueError(
                f"people: {people.shape[0]} rows, the previous frame had {self.people.shape[0]}; "
                "keep one row per track id (present = False where not seen)"
            )
        present = _presence(present, people)
        pose = jnp.asarray(pose, jnp.float32)
        return Frame(pose, people, present, self.people, self.present, self.t + 1)


def _points(name: str, x: Any) -> Array:
    """x as float32 [S, 2] (an empty list: no obstacle); ValueError naming `name` otherwise."""
    x = jnp.asarray(x, jnp.float32)
    if x.size == 0:
        return jnp.zeros((0, 2), jnp.float32)
    _check(name, x, (None, 2), "one (x, y) row per obstacle, in metres")
    return x


def _radii(radius: Any, points: Array) -> Array:
    r = jnp.asarray(radius, jnp.float32)
    if r.ndim > 0:
        _check("radius", r, (points.shape[0],), "one per obstacle, or one for all")
    return jnp.broadcast_to(r, points.shape[:1])


def _people(people: Any) -> Array:
    people = jnp.asarray(people, jnp.float32)
    return jnp.zeros((0, 2), jnp.float32) if people.size == 0 else people


def _presence(present: Any, people: Array) -> Array:
    if present is None:
        return jnp.ones(people.shape[:1], bool)
    return jnp.asarray(present, bool)


# ------------------------------------------------------------------------------ layout
@dataclasses.dataclass(frozen=True)
class Layout:
    """What fixes the observation of a trained policy: the env config it was trained with (its
    observation options included) and the numbers of people and static obstacles it saw. Frozen
    and hashable: a static argument under `jit`."""

    config: NavConfig
    num_people: int
    num_static: int

    @property
    def obs_dim(self) -> int:
        return observation_dim(self.config, self.num_people, self.num_static)

    @property
    def uses_static(self) -> bool:
        """Whether the observation holds per-obstacle entries (then the scene must have exactly
        `num_static` obstacles, in the order the policy was trained with)."""
        return self.config.observe_static or self.config.observe_relative

    def parts(self) -> list[dict]:
        """The observation's parts: [{name, start, size, meaning}]."""
        return observation_layout(self.config, self.num_people, self.num_static)

    @classmethod
    def of(cls, policy: Any) -> Layout:
        """The layout of a `LoadedPolicy` (from its run config) or an exported policy (from its
        sidecar)."""
        meta = getattr(policy, "meta", None)
        if isinstance(meta, dict):  # exported.ExportedPolicy
            obs = meta["observation"]
            config = nav_config_from_dict(meta["env_config"])
            return cls(config, int(obs["num_people"]), int(obs["num_static"]))
        return layout_of_run(policy.config, policy.obs_dim)


def nav_config_from_dict(d: dict) -> NavConfig:
    """A NavConfig from its JSON form (lists for the arena corners)."""
    fields = {f.name for f in dataclasses.fields(NavConfig)}
    kw: dict[str, Any] = {
        k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in fields
    }
    return NavConfig(**kw)


def layout_of_run(config: Any, obs_dim: int) -> Layout:
    """The layout of a run (an ExperimentConfig) whose policy takes observations of `obs_dim`.
    The numbers of people and obstacles come from the family's test tasks (built without the
    run's data file: only their shapes are read)."""
    from mpcpearl_jax.envs import make_env

    nav = make_env(config.env, **config.env_overrides).config
    num_people, num_static = _family_counts(config.env, nav)
    out = Layout(nav, num_people, num_static)
    if out.obs_dim != obs_dim:
        raise ValueError(
            f"{config.env}: the policy takes observations of {obs_dim} entries, but "
            f"{num_people} people and {num_static} obstacles under the run's options give "
            f"{out.obs_dim}"
        )
    return out


@functools.cache
def _family_counts(name: str, nav: NavConfig) -> tuple[int, int]:
    from mpcpearl_jax.envs import make_tasks

    tasks = make_tasks(name, "test", 0, config=nav)
    return int(tasks.human_pos.shape[-2]), int(tasks.static_lo.shape[-2])


# ------------------------------------------------------------------------------ checks
def _is_traced(x: Any) -> bool:
    return isinstance(x, jax.core.Tracer)


def _check(name: str, x: Any, shape: tuple, what: str, finite: Any = True) -> None:
    """ValueError naming `name` if x's shape is not `shape` (None: any size) or, for a concrete
    x, if the entries selected by `finite` (True: all) hold NaN or inf."""
    got = tuple(np.shape(x))
    if len(got) != len(shape) or any(
        s is not None and s != g for s, g in zip(shape, got, strict=True)
    ):
        want = "[" + ", ".join("N" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want} ({what}), got {list(got)}")
    if finite is False or _is_traced(x) or _is_traced(finite):
        return
    bad = ~np.isfinite(np.asarray(x, np.float64))
    if finite is not True:
        bad = bad & np.asarray(finite, bool).reshape(np.shape(finite) + (1,) * (bad.ndim - 1))
    if bad.any():
        raise ValueError(f"{name}: contains NaN or inf ({what})")


def check_frame(frame: Frame, name: str = "frame") -> None:
    """Shapes of a frame (always) and finite values (when concrete): the pose, and the people
    marked present. ValueError naming the field."""
    if not isinstance(frame, Frame):
        raise TypeError(f"{name}: expected a deploy.Frame, got {type(frame).__name__}")
    _check(f"{name}.pose", frame.pose, (3,), "x, y in metres, heading in radians")
    n = np.shape(frame.people)[0] if np.ndim(frame.people) == 2 else None
    _check(f"{name}.present", frame.present, (n,), "one flag per row of people", False)
    _check(f"{name}.prev_present", frame.prev_present, (n,), "one flag per row of people", False)
    _check(f"{name}.people", frame.people, (n, 2), "people positions in metres", frame.present)
    what = "the same people a step earlier"
    _check(f"{name}.prev_people", frame.prev_people, (n, 2), what, frame.prev_present)
    _check(f"{name}.t", frame.t, (), "steps since the episode began")
    if not jnp.issubdtype(jnp.asarray(frame.t).dtype, jnp.integer):
        raise ValueError(f"{name}.t: expected an integer step count, got {jnp.asarray(frame.t)}")
    if not _is_traced(frame.t) and int(frame.t) < 0:
        raise ValueError(f"{name}.t: expected steps since the episode began (>= 0), got {frame.t}")


def check_scene(scene: Scene, layout: Layout | None = None, name: str = "scene") -> None:
    """Shapes and finite values of a scene; with a layout whose observation lists the static
    obstacles, their number must be the trained one. ValueError naming the field."""
    if not isinstance(scene, Scene):
        raise TypeError(f"{name}: expected a deploy.Scene, got {type(scene).__name__}")
    _check(f"{name}.goal", scene.goal, (2,), "goal position in metres")
    s = np.shape(scene.static_lo)[0] if np.ndim(scene.static_lo) == 2 else None
    if layout is not None and layout.uses_static:
        s = layout.num_static
    what = "static obstacles" + (" (as many as the policy was trained with)" if s else "")
    _check(f"{name}.static_lo", scene.static_lo, (s, 2), what)
    _check(f"{name}.static_hi", scene.static_hi, (s, 2), what)
    _check(f"{name}.static_radius", scene.static_radius, (s,), what)
    if any(_is_traced(x) for x in scene):
        return
    lo, hi = np.asarray(scene.static_lo, np.float64), np.asarray(scene.static_hi, np.float64)
    radius, goal = np.asarray(scene.static_radius, np.float64), np.asarray(scene.goal, np.float64)
    if (radius < 0).any():
        k = int(np.argmax(radius < 0))
        raise ValueError(f"{name}.static_radius: obstacle {k} has a negative radius {radius[k]}")
    if (hi < lo).any():
        k = int(np.argmax((hi < lo).any(axis=-1)))
        raise ValueError(f"{name}.static_hi: obstacle {k} has hi {hi[k]} below lo {lo[k]}")
    dist = np.linalg.norm(np.maximum(np.maximum(lo - goal, goal - hi), 0.0), axis=-1)
    inside = (dist < radius) | np.all((goal > lo) & (goal < hi), axis=-1)
    if inside.any():
        k = int(np.argmax(inside))
        raise ValueError(
            f"{name}.goal: {goal.tolist()} lies inside static obstacle {k} (box {lo[k].tolist()}"
            f" to {hi[k].tolist()}, radius {radius[k]:g}); no robot can reach it"
        )


def check_action(action: Any, name: str = "action") -> None:
    """Shape and finite values, and for a concrete action the range [-1, 1] of the policy's
    normalized actions (a physical command such as (7 m/s, 0) is refused, naming `command`)."""
    _check(name, action, (2,), "normalized (speed, steering) in [-1, 1]")
    if _is_traced(action):
        return
    a = np.asarray(action, np.float64)
    if (np.abs(a) > 1.0 + 1e-6).any():
        raise ValueError(
            f"{name}: expected a normalized (speed, steering) in [-1, 1], got {a.tolist()}; "
            "give the policy's action, not the physical command (Adapter.command maps one to "
            "the other)"
        )


# ------------------------------------------------------------------------------ observe
def fit_people(frame: Frame, num_people: int) -> tuple[Array, Array, Array, Array]:
    """(people, present, prev_people, prev_present) with exactly `num_people` rows: fewer rows
    are padded with absent people, of more rows the `num_people` nearest present ones are kept
    (in their row order). Absent rows are zeroed, so that their content never matters."""
    people, present = frame.people, frame.present.astype(bool)
    prev, prev_present = frame.prev_people, frame.prev_present.astype(bool)
    n = people.shape[0]
    if n > num_people:
        dist = jnp.linalg.norm(people - frame.pose[:2], axis=-1)
        keep = jnp.argsort(jnp.where(present, dist, jnp.inf), stable=True)[:num_people]
        keep = jnp.sort(keep)
        people, present, prev, prev_present = (
            x[keep] for x in (people, present, prev, prev_present)
        )
    elif n < num_people:
        pad = num_people - n
        people, prev = (jnp.concatenate([x, jnp.zeros((pad, 2), x.dtype)]) for x in (people, prev))
        present, prev_present = (
            jnp.concatenate([x, jnp.zeros((pad,), bool)]) for x in (present, prev_present)
        )
    people = jnp.where(present[:, None], people, 0.0)
    prev = jnp.where(prev_present[:, None], prev, 0.0)
    return people, present, prev, prev_present


def observe(layout: Layout, frame: Frame, scene: Scene) -> Array:
    """The observation [layout.obs_dim] the policy was trained on, from raw arrays.

    Pure and jittable (`jax.jit(observe, static_argnums=0)`); equal to `NavEnv.observe` on the
    env's own state. People beyond the trained number: the nearest present ones are kept; fewer:
    the rest count as absent. A step t beyond the episode length reads as the last step (the
    policy never saw later ones). Shapes are checked always, values (NaN or inf in the pose, a
    present person, the goal or an obstacle) when concrete: a ValueError naming the field.
    """
    check_frame(frame)
    check_scene(scene, layout)
    people, present, prev, prev_present = fit_people(frame, layout.num_people)
    t = jnp.clip(jnp.asarray(frame.t), 0, layout.config.horizon)
    return observation(
        layout.config,
        jnp.asarray(frame.pose, jnp.float32),
        t,
        people,
        present,
        prev,
        prev_present,
        jnp.asarray(scene.static_lo, jnp.float32),
        jnp.asarray(scene.static_hi, jnp.float32),
        jnp.asarray(scene.goal, jnp.float32),
    )


# ------------------------------------------------------------------------------ reward
def command(config: NavConfig, action: Array, pose: Array, goal: Array) -> Array:
    """The physical input (v in m/s, steering delta in rad) [2] of a normalized action [2], as
    the env applies it: mapped onto [0, v_max] x [-pi/2, pi/2], speed 0 once the robot is
    within its radius of the goal (parked, method §2)."""
    u = to_physical(action, config.v_max)
    parked = jnp.linalg.norm(pose[:2] - goal) <= config.robot_radius
    return u.at[0].set(jnp.where(parked, 0.0, u[0]))


def reward(config: NavConfig, frame: Frame, action: Array, next_frame: Frame, scene: Scene):
    """The reward of eq. (2) for the transition frame -> next_frame under `action` [2], as the
    env pays it: (reward [], collision []).

    The quadratic cost uses the pose at t and the applied input (`command`); the safety counts
    n_d, n_s (every person present at t + 1, all of them, not only those the policy sees) and
    the contact test use the position the bicycle model of eq. (1) predicts from the pose and
    input, i.e. the attempted move, which is the measured next position unless a contact
    stopped the robot; the goal bonus uses the measured next position.
    """
    pose, goal = frame.pose, scene.goal
    u = command(config, action, pose, goal)
    attempted = bicycle_step(pose, u, config.dt, config.wheelbase)
    p = physics.clip_to_arena(attempted[:2], config)
    people, present = next_frame.people, next_frame.present.astype(bool)
    people = jnp.where(present[:, None], people, 0.0)
    n_d, n_s = physics.safety_violations(p, people, present, scene, config)
    collision = physics.collides(p, people, present, scene, config)
    r = physics.reward(pose[:2], u, n_d, n_s, next_frame.pose[:2], goal, config)
    return r, collision


# ------------------------------------------------------------------------------ adapter
class AdapterState(NamedTuple):
    """What the adapter carries from step to step (a pytree: jit, save or copy it freely).

    context [C, D] rows (s, a, r, s'), mask [C] (1 = a row holds a transition), added [] the
    transitions added so far (the newest C are kept), z [L] the latent the policy acts with,
    keys [C, 2] the keys of the paper's z re-sampling (None: z is the posterior mean), and the
    task's scene."""

    context: Array
    mask: Array
    added: Array
    z: Array
    keys: Array | None
    scene: Scene


class Adapter:
    """Online adaptation step by step (method §7; paper Algorithm 2, online): the policy acts
    with z, every transition is stored as a context row with the reward of eq. (2), and every
    `t_update` transitions z is re-inferred from all rows so far.

    Stateless: `init(scene, key)`, `act(state, frame)`, `add(state, frame, action, next_frame)`
    and `z(state)` are pure functions of their arguments (jitted once per input shape). A new
    task (another goal or obstacles) starts from `init` again; further episodes of the same task
    keep adding to the same state, their frames starting again at t = 0.

    policy: a `LoadedPolicy` (`load_policy`) or an exported policy (`load_exported`): anything
    with `act(obs, z)` and `infer_z(context, mask, key)`.
    layout: default `Layout.of(policy)`. t_update: default the run's (5 in the paper).
    capacity: context rows kept, default one episode (the env's horizon).
    """

    def __init__(
        self,
        policy: Any,
        layout: Layout | None = None,
        t_update: int | None = None,
        capacity: int | None = None,
    ):
        self.policy = policy
        self.layout = layout or Layout.of(policy)
        if self.layout.obs_dim != policy.obs_dim:
            raise ValueError(
                f"layout: gives observations of {self.layout.obs_dim} entries, the policy takes "
                f"{policy.obs_dim}"
            )
        self.t_update = _run_t_update(policy) if t_update is None else t_update
        self.capacity = self.layout.config.horizon if capacity is None else capacity
        for name, v in (("t_update", self.t_update), ("capacity", self.capacity)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name}: must be a positive int, got {v!r}")
        self._observe = jax.jit(observe, static_argnums=0)
        self._act = jax.jit(self._act_impl)
        self._add = jax.jit(self._add_impl)

    @property
    def config(self) -> NavConfig:
        return self.layout.config

    def init(self, scene: Scene, key: Array | None = None) -> AdapterState:
        """An empty context for the task `scene`; z from the prior: a sample with `key` (the
        paper's protocol), else its mean 0."""
        check_scene(scene, self.layout)
        scene = Scene(*(jnp.asarray(x, jnp.float32) for x in scene))
        c, d, lat = self.capacity, self.policy.context_dim, self.policy.latent_dim
        context, mask = jnp.zeros((c, d), jnp.float32), jnp.zeros((c,), jnp.float32)
        keys = None
        if check_key(key) is not None:
            k0, k_run = jax.random.split(key)
            z = self.policy.infer_z(context, mask, k0)  # the prior: the mask selects no row
            keys = jax.random.split(k_run, c)
        else:
            z = jnp.zeros((lat,), jnp.float32)
        return AdapterState(context, mask, jnp.zeros((), jnp.int32), z, keys, scene)

    def observe(self, state: AdapterState, frame: Frame) -> Array:
        """The policy's observation [O] of `frame` in the state's scene."""
        return self._observe(self.layout, frame, state.scene)

    def act(self, state: AdapterState, frame: Frame) -> Array:
        """The deterministic action [2] in [-1, 1]^2 (tanh of the mean) for `frame`."""
        check_frame(frame)
        return self._act(state, frame)

    def add(self, state: AdapterState, frame: Frame, action: Any, next_frame: Frame):
        """The state after the transition frame -> next_frame under `action`: its context row
        (s, a, r, s') with the reward of eq. (2) appended (the oldest overwritten once
        `capacity` rows are held), and z re-inferred when the number added reaches a multiple of
        `t_update`."""
        check_frame(frame)
        check_frame(next_frame, "next_frame")
        check_action(action)
        return self._add(state, frame, jnp.asarray(action, jnp.float32), next_frame)

    def z(self, state: AdapterState) -> Array:
        """The latent [L] the next action is taken with."""
        return state.z

    def command(self, state: AdapterState, frame: Frame, action: Array) -> Array:
        """The physical input (v m/s, delta rad) [2] to send to the robot (see `command`)."""
        return command(self.config, jnp.asarray(action), frame.pose, state.scene.goal)

    def reward(self, state: AdapterState, frame: Frame, action: Any, next_frame: Frame):
        """(reward, collision) of a transition (see `reward`)."""
        return reward(self.config, frame, jnp.asarray(action), next_frame, state.scene)

    # -- jitted bodies
    def _act_impl(self, state: AdapterState, frame: Frame) -> Array:
        obs = observe(self.layout, frame, state.scene)
        return self.policy.act(obs, state.z)

    def _add_impl(self, state: AdapterState, frame: Frame, action: Array, next_frame: Frame):
        obs = observe(self.layout, frame, state.scene)
        next_obs = observe(self.layout, next_frame, state.scene)
        r, _ = reward(self.config, frame, action, next_frame, state.scene)
        row = jnp.concatenate([obs, action, r[None], next_obs]).astype(jnp.float32)
        i = state.added % self.capacity
        context = state.context.at[i].set(row)
        mask = state.mask.at[i].set(1.0)
        added = state.added + 1
        key = None if state.keys is None else state.keys[added % self.capacity]
        z_new = self.policy.infer_z(context, mask, key)
        z = jnp.where(added % self.t_update == 0, z_new, state.z)
        return AdapterState(context, mask, added, z, state.keys, state.scene)


def _run_t_update(policy: Any) -> int:
    meta = getattr(policy, "meta", None)
    if isinstance(meta, dict):
        return int(meta["t_update"])
    return int(policy.config.train.t_update)
