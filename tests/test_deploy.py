"""`deploy.observe` and `deploy.reward` from raw arrays equal the env's own observation and
reward at every step of episodes of both task families, under every committed run's env options;
the observation options against a NumPy reference; padding, nearest-kept people and clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.deploy.adapter import Frame, Layout, Scene, check_frame, observe, reward
from mpcpearl_jax.envs import EnvState, make_env, make_tasks

ROOT = Path(__file__).resolve().parents[1]


def _committed_options() -> list[tuple[str, dict]]:
    """Every distinct (family, env overrides) of the committed runs under results/ (an option
    since removed dropped, as loading the run does: `config.REMOVED_OPTIONS`)."""
    from mpcpearl_jax.config import REMOVED_OPTIONS

    seen: dict[str, tuple[str, dict]] = {}
    for path in sorted((ROOT / "results").rglob("config.json")):
        cfg = json.loads(path.read_text())
        if "env" not in cfg:
            continue
        removed = REMOVED_OPTIONS["env_overrides"]
        over = {k: v for k, v in (cfg.get("env_overrides") or {}).items() if k not in removed}
        seen.setdefault(json.dumps([cfg["env"], over], sort_keys=True), (cfg["env"], over))
    return list(seen.values())


OPTIONS = _committed_options()
_TASKS: dict = {}


def _tasks(env):
    name = env.config.name
    if name not in _TASKS:
        _TASKS[name] = make_tasks(name, "test", 0, config=env.config)  # synthetic sidewalk crowd
    return _TASKS[name]


def _frame(env, task, state) -> Frame:
    humans, mask = env.humans_at(task, state.t)
    prev, prev_mask = env.humans_at(task, jnp.maximum(state.t - 1, 0))
    return Frame(state.pose, humans, mask, prev, prev_mask, state.t)


def _actions(key, task, state, i):
    """Half the episodes drive at the goal, half at random, both noisy: many contacts."""
    to_goal = task.goal - state.pose[:2]
    err = jnp.arctan2(to_goal[1], to_goal[0]) - state.pose[2]
    steer = jnp.clip(jnp.arctan2(jnp.sin(err), jnp.cos(err)) / (jnp.pi / 2), -1.0, 1.0)
    noise = jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0)
    seek = jnp.stack([0.3, steer]) + 0.3 * noise
    return jnp.where(i % 2 == 0, seek, noise)


def _rollout_both(env, layout):
    """Per task and step: (env obs, raw obs, env reward, raw reward, collision) [N, T, ...]."""

    def episode(task, i):
        # a quarter of the episodes start 1.5 m from the goal: the bonus and parking
        near = jnp.concatenate([task.goal + jnp.array([-1.5, 0.3]), jnp.zeros(1)])
        task = task.replace(start=jnp.where(i % 4 == 1, near, task.start))
        obs0, state0 = env.reset(jax.random.PRNGKey(0), task)
        scene = Scene.from_task(task)

        def body(carry, k):
            obs, state = carry
            frame = _frame(env, task, state)
            raw = observe(layout, frame, scene)
            a = _actions(k, task, state, i)
            nobs, nstate, r, _, info = env.step(k, state, a, task)
            r_raw, col_raw = reward(env.config, frame, a, _frame(env, task, nstate), scene)
            out = (obs, raw, r, r_raw, info.collision, col_raw, info.n_dynamic + info.n_static)
            return (nobs, nstate), out

        keys = jax.random.split(jax.random.PRNGKey(i), env.config.horizon)
        (last_obs, last_state), out = jax.lax.scan(body, (obs0, state0), keys)
        final = observe(layout, _frame(env, task, last_state), scene)
        return out, last_obs, final

    tasks = _tasks(env)
    return jax.jit(jax.vmap(episode))(tasks, jnp.arange(tasks.num_tasks))


@pytest.mark.parametrize("family,overrides", OPTIONS, ids=[json.dumps(o) for o in OPTIONS])
def test_observe_and_reward_equal_the_env_at_every_step(family, overrides):
    env = make_env(family, **overrides)
    tasks = _tasks(env)
    layout = Layout(env.config, tasks.human_pos.shape[-2], tasks.static_lo.shape[-2])
    out, last_obs, final = _rollout_both(env, layout)
    obs, raw, r, r_raw, col, col_raw, violations = map(np.asarray, out)
    assert raw.shape[-1] == layout.obs_dim == env.obs_dim(tasks)
    # equal up to float rounding of the same operations compiled in two places (1 ulp)
    np.testing.assert_allclose(raw, obs, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(final), np.asarray(last_obs), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(col_raw, col)
    np.testing.assert_allclose(r_raw, r, rtol=0, atol=1e-5)
    # the episodes exercised the reward's every term
    assert col.any() and (violations > 0).any() and (r > 0).any()


# ------------------------------------------------------------------ NumPy reference
def _np_observe(cfg, pose, t, people, present, prev, prev_present, lo, hi, goal):
    """The observation written out in NumPy, one option at a time."""
    a_lo, a_hi = np.asarray(cfg.arena_lo), np.asarray(cfg.arena_hi)
    scale = lambda p: np.clip(2.0 * (p - a_lo) / (a_hi - a_lo) - 1.0, -1.0, 1.0)
    dist = np.linalg.norm(people - pose[:2], axis=-1)
    if cfg.sensing_radius > 0:
        present = present & (dist <= cfg.sensing_radius)
    if cfg.observe_sorted:
        order = np.argsort(np.where(present, dist, np.inf), kind="stable")
        people, present, prev, prev_present = (
            x[order] for x in (people, present, prev, prev_present)
        )
    parts = [scale(pose[:2]), [pose[2] / np.pi], np.where(present[:, None], scale(people), -1.0)]
    if cfg.observe_velocity:
        vel = np.clip((people - prev) / (cfg.velocity_scale * cfg.dt), -1, 1)
        parts.append(np.where((present & prev_present)[:, None], vel, 0.0))
    if cfg.observe_static:
        parts.append(scale((lo + hi) / 2))
    if cfg.observe_relative:
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rot = np.array([[c, s], [-s, c]])
        ego = lambda q: np.clip((q - pose[:2]) @ rot.T / cfg.relative_scale, -1, 1)
        parts.append(np.where(present[:, None], ego(people), 1.0))
        parts.append(ego(np.clip(pose[:2], lo, hi)))
        parts.append(ego(goal[None]))
    if cfg.observe_time:
        parts.append([2.0 * t / cfg.horizon - 1.0])
    return np.concatenate([np.ravel(p) for p in parts])


ALL_OPTIONS = dict(
    observe_velocity=True,
    observe_relative=True,
    observe_sorted=True,
    observe_time=True,
    sensing_radius=3.0,
)


@pytest.mark.parametrize(
    "overrides",
    [{}, ALL_OPTIONS, {**ALL_OPTIONS, "observe_sorted": False, "sensing_radius": 0.0}],
    ids=["paper", "all-options", "unsorted-unlimited"],
)
def test_observe_equals_a_numpy_reference(overrides):
    env = make_env("restaurant", **overrides)
    tasks = _tasks(make_env("restaurant"))
    layout = Layout(env.config, 6, 5)
    fn = jax.jit(chex.assert_max_traces(lambda f, s: observe(layout, f, s), n=1))
    chex.clear_trace_counter()
    rng = np.random.default_rng(0)
    for i in range(12):
        task = jax.tree_util.tree_map(lambda x, i=i: x[i], tasks)
        t = int(rng.integers(1, 80))
        pose = np.array([*rng.uniform(-4.5, 4.5, 2), rng.uniform(-np.pi, np.pi)], np.float32)
        people = np.asarray(task.human_pos[t]) + rng.normal(0, 0.5, (6, 2)).astype(np.float32)
        prev = people + rng.normal(0, 0.1, (6, 2)).astype(np.float32)
        present, prev_present = rng.random(6) < 0.8, rng.random(6) < 0.8
        frame = Frame(*map(jnp.asarray, (pose, people, present, prev, prev_present)), jnp.int32(t))
        lo, hi, goal = (np.asarray(x) for x in (task.static_lo, task.static_hi, task.goal))
        want = _np_observe(env.config, pose, t, people, present, prev, prev_present, lo, hi, goal)
        np.testing.assert_allclose(np.asarray(fn(frame, Scene.from_task(task))), want, atol=2e-6)


# ------------------------------------------------------------------ more or fewer people
@pytest.fixture(scope="module")
def headline_env():
    cfg = json.loads((ROOT / "results/restaurant/mpc-pearl-eps0.2/config.json").read_text())
    return make_env("restaurant", **cfg["env_overrides"])


def _env_obs_and_frame(env, t=30, i=5):
    task = jax.tree_util.tree_map(lambda x: x[i], _tasks(env))
    state = EnvState(jnp.array([-1.0, 0.8, 0.3]), jnp.int32(t))
    return env.observe(state, task), _frame(env, task, state), Scene.from_task(task), task


def test_more_people_than_trained_keeps_the_nearest(headline_env):
    env = headline_env
    want, frame, scene, _ = _env_obs_and_frame(env)
    layout = Layout(env.config, 6, 5)
    # three more people far away, in front of the real ones: the six nearest are the task's
    far = jnp.array([[40.0, 40.0], [-30.0, 10.0], [25.0, -35.0]])
    more = Frame(
        frame.pose,
        jnp.concatenate([far, frame.people]),
        jnp.concatenate([jnp.ones(3, bool), frame.present]),
        jnp.concatenate([far, frame.prev_people]),
        jnp.concatenate([jnp.ones(3, bool), frame.prev_present]),
        frame.t,
    )
    np.testing.assert_array_equal(np.asarray(observe(layout, more, scene)), np.asarray(want))
    # a near extra person displaces the farthest one
    near = more._replace(people=more.people.at[0].set(frame.pose[:2] + 0.6))
    obs = np.asarray(observe(layout, near, scene))
    assert not np.array_equal(obs, np.asarray(want))


def test_fewer_people_than_trained_count_as_absent(headline_env):
    env = headline_env
    _, frame, scene, task = _env_obs_and_frame(env)
    layout = Layout(env.config, 6, 5)
    fewer = Frame(
        frame.pose,
        frame.people[:4],
        frame.present[:4],
        frame.prev_people[:4],
        frame.prev_present[:4],
        frame.t,
    )
    gone = frame._replace(present=frame.present.at[4:].set(False))
    np.testing.assert_array_equal(
        np.asarray(observe(layout, fewer, scene)), np.asarray(observe(layout, gone, scene))
    )
    # nobody in sight at all, and absent rows holding NaN
    empty = Frame.start(frame.pose, jnp.zeros((0, 2)))
    assert observe(layout, empty, scene).shape == (layout.obs_dim,)
    nan_absent = gone._replace(people=gone.people.at[4:].set(jnp.nan))
    np.testing.assert_array_equal(
        np.asarray(observe(layout, nan_absent, scene)), np.asarray(observe(layout, gone, scene))
    )


def test_frame_start_and_advance_match_the_env(headline_env):
    env = headline_env
    task = jax.tree_util.tree_map(lambda x: x[2], _tasks(env))
    layout, scene = Layout(env.config, 6, 5), Scene.from_task(task)
    obs, state = env.reset(jax.random.PRNGKey(0), task)
    frame = Frame.start(state.pose, task.human_pos[0], task.human_mask[0])
    for t in range(4):
        np.testing.assert_array_equal(np.asarray(observe(layout, frame, scene)), np.asarray(obs))
        obs, state, *_ = env.step(jax.random.PRNGKey(t), state, jnp.array([0.3, -0.2]), task)
        frame = frame.advance(state.pose, task.human_pos[t + 1], task.human_mask[t + 1])


def test_scene_constructors():
    tables = Scene.circles([3.5, -3.5], [[0.0, 0.0], [2.5, 0.0]], 0.5)
    assert tables.static_lo.shape == (2, 2) and tables.static_radius.tolist() == [0.5, 0.5]
    walls = Scene.boxes([14.0, 5.0], [[0.0, 7.0]], [[9.5, 20.0]])
    assert walls.static_radius.tolist() == [0.0]
    assert Scene.circles([0.0, 0.0], [], 0.5).static_lo.shape == (0, 2)
    with pytest.raises(ValueError, match=r"^centres: expected shape \[N, 2\]"):
        Scene.circles([3.5, -3.5], [[0.0, 0.0, 1.0], [2.5, 0.0, 1.0]], 0.5)
    with pytest.raises(ValueError, match=r"^radius: expected shape \[2\]"):
        Scene.circles([3.5, -3.5], [[0.0, 0.0], [2.5, 0.0]], [0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match=r"^hi: expected shape \[1, 2\] \(as lo\)"):
        Scene.boxes([14.0, 5.0], [[0.0, 7.0]], [[9.5, 20.0], [1.0, 1.0]])


# ------------------------------------------------------------------ errors
def test_bad_inputs_are_one_line_errors_naming_the_argument(headline_env):
    _, frame, scene, _ = _env_obs_and_frame(headline_env)
    layout = Layout(headline_env.config, 6, 5)
    cases = [
        (frame._replace(pose=frame.pose[:2]), scene, r"frame\.pose: expected shape \[3\]"),
        (frame._replace(pose=frame.pose.at[0].set(jnp.nan)), scene, r"frame\.pose: contains NaN"),
        (frame._replace(people=frame.people[:, :1]), scene, r"frame\.people: expected shape"),
        (frame._replace(present=frame.present[:3]), scene, r"frame\.present: expected shape"),
        (
            frame._replace(
                people=frame.people.at[0].set(jnp.inf), present=frame.present.at[0].set(True)
            ),
            scene,
            r"frame\.people: contains NaN or inf",
        ),
        (frame._replace(t=jnp.float32(3.0)), scene, r"frame\.t: expected an integer"),
        (frame, scene._replace(goal=jnp.array([jnp.nan, 0.0])), r"scene\.goal: contains NaN"),
        (frame, scene._replace(static_lo=scene.static_lo[:4]), r"scene\.static_lo: .*\[5, 2\]"),
    ]
    for f, s, match in cases:
        with pytest.raises(ValueError, match=match) as e:
            observe(layout, f, s)
        assert "\n" not in str(e.value)
    with pytest.raises(TypeError, match="frame: expected a deploy.Frame"):
        check_frame((frame.pose,))
    with pytest.raises(ValueError, match=r"^people: 5 rows, the previous frame had 6; keep one"):
        frame.advance(frame.pose, frame.people[:5])
