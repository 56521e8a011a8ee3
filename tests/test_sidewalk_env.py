"""The sidewalk environment (method §4): boxes, observation, masked people, step vs NumPy twin."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.envs import EnvState, make_env, make_tasks, physics
from mpcpearl_jax.envs.numpy_ref import NumpyNavEnv, rounded_box_clearance, task_to_numpy
from mpcpearl_jax.envs.sidewalk import SIDEWALK_CONFIG, sidewalk_boxes

ZARA = Path(__file__).resolve().parents[2] / "shared" / "data" / "crowds_zara01.txt"
ATOL = 1e-5
MARGIN = 1e-4  # samples this close to a threshold are ambiguous between float32 and float64

# Hand-computed Euclidean distances to the four boxes (building, car 1, car 2, road).
#   building: x <= 9.5, y >= 7.0      car 1: x in [9.8, 11.7], y >= 10.2
#   car 2: x in [9.9, 11.9], y in [5.5, 10.3]       road: y <= 1.9
BOX_TABLE = [
    # point         building          car 1             car 2              road
    ((1.0, 6.0), (1.0, np.hypot(8.8, 4.2), 8.9, 4.1)),
    ((14.0, 5.0), (np.hypot(4.5, 2.0), np.hypot(2.3, 5.2), np.hypot(2.1, 0.5), 3.1)),
    ((9.7, 7.5), (0.2, np.hypot(0.1, 2.7), 0.2, 5.6)),
    ((10.5, 10.25), (1.0, 0.0, 0.0, 8.35)),
    ((12.5, 11.0), (3.0, 0.8, np.hypot(0.6, 0.7), 9.1)),
    ((5.0, 1.0), (6.0, np.hypot(4.8, 9.2), np.hypot(4.9, 4.5), 0.0)),
    ((9.0, 8.0), (0.0, np.hypot(0.8, 2.2), 0.9, 6.1)),
    ((0.2, 12.2), (0.0, 9.6, np.hypot(9.7, 1.9), 10.3)),
]


def _take(params, i):
    return jax.tree_util.tree_map(lambda x: x[i], params)


@pytest.fixture(scope="module")
def env():
    return make_env("sidewalk")


@pytest.fixture(scope="module", params=["synthetic", "zara"])
def tasks(request):
    if request.param == "zara":
        if not ZARA.is_file():
            pytest.skip(f"UCY Zara 01 data not found at {ZARA}")
        return make_tasks("sidewalk", "test", data=ZARA)
    return make_tasks("sidewalk", "test", seed=0)


def test_config_matches_spec(env):
    cfg = env.config
    assert (cfg.name, cfg.dt, cfg.horizon, cfg.v_max) == ("sidewalk", 0.04, 250, 1.8)
    assert cfg.arena_lo == (-0.021, -0.239) and cfg.arena_hi == (15.132, 12.386)
    assert not cfg.observe_static
    assert make_env("sidewalk", v_max=2.0).config.v_max == 2.0


@pytest.mark.parametrize("point, expected", BOX_TABLE)
def test_box_distance_against_hand_table(point, expected):
    lo, hi, _ = sidewalk_boxes(SIDEWALK_CONFIG)
    got = physics.box_distance(jnp.asarray(point, jnp.float32)[None, :], lo, hi)
    np.testing.assert_allclose(np.asarray(got), expected, atol=ATOL)
    twin = rounded_box_clearance(
        np.asarray(point, float), lo.astype(float), hi.astype(float), np.zeros(4)
    )
    np.testing.assert_allclose(twin, expected, atol=ATOL)


def test_far_box_edges_are_float32_exact():
    lo, hi, _ = sidewalk_boxes(SIDEWALK_CONFIG)
    assert lo.dtype == np.float32 and np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))
    # the half-infinite sides lie far outside the arena
    assert lo[0, 0] < -900 and hi[0, 1] > 900 and hi[1, 1] > 900 and lo[3, 1] < -900
    # near the finite edges, float32 distances match float64 ones to 1e-6 m
    rng = np.random.default_rng(0)
    pts = rng.uniform((-0.021, -0.239), (15.132, 12.386), size=(500, 2))
    d32 = np.asarray(physics.box_distance(jnp.asarray(pts[:, None], jnp.float32), lo, hi))
    d64 = np.stack(
        [rounded_box_clearance(p, lo.astype(float), hi.astype(float), np.zeros(4)) for p in pts]
    )
    np.testing.assert_allclose(d32, d64, atol=1e-5)


def test_start_and_goal_are_clear(env, tasks):
    cfg = env.config
    task = _take(tasks, 0)
    for p in (task.start[:2], task.goal):
        clear = physics.static_clearance(p, task)
        assert float(jnp.min(clear)) >= cfg.robot_radius + cfg.r_safe


def test_observation_is_pose_and_five_people(env, tasks):
    task = _take(tasks, 0)
    obs, state = env.reset(jax.random.PRNGKey(0), task)
    assert obs.shape == (13,) and env.obs_dim(task) == 13
    assert np.all(np.abs(np.asarray(obs)) <= 1.0)
    hidden = task.replace(human_mask=task.human_mask.at[0, 2].set(False))
    obs_h = env.observe(state, hidden)
    np.testing.assert_array_equal(np.asarray(obs_h[7:9]), [-1.0, -1.0])


def _place_person(task, t, slot, xy, present):
    pos = task.human_pos.at[t, slot].set(jnp.asarray(xy, jnp.float32))
    return task.replace(human_pos=pos, human_mask=task.human_mask.at[t, slot].set(present))


@pytest.mark.parametrize("present", [True, False])
def test_absent_people_are_no_obstacle_and_fire_no_event(env, tasks, present):
    """A person exactly where the robot goes: collision and event only when present."""
    task = _take(tasks, 0)
    task = task.replace(human_mask=jnp.zeros_like(task.human_mask))  # nobody else around
    t = 40
    pose = jnp.asarray([3.0, 4.0, 0.0], jnp.float32)
    action = jnp.asarray([-1.0, 0.0])  # v = 0: the robot stays put
    task = _place_person(task, t, 1, (3.0, 4.0), present)
    task = _place_person(task, t + 1, 1, (3.1, 4.0), present)
    state = EnvState(pose=pose, t=jnp.asarray(t, jnp.int32))
    _, _, r, _, info = env.step(jax.random.PRNGKey(0), state, action, task)
    assert bool(info.collision) == present
    assert int(info.n_dynamic) == int(present)
    assert bool(info.event) == present
    assert bool(env.event(state, task)) == present
    assert (float(r) < -19.0) == present


def _sample_states(rng, task, cfg, n):
    """Poses [n, 3] and steps [n] near people, boxes, the goal and anywhere in the arena."""
    lo = np.asarray(cfg.arena_lo) + cfg.robot_radius
    hi = np.asarray(cfg.arena_hi) - cfg.robot_radius
    poses, steps = [], []
    present = np.argwhere(task["human_mask"][1:])
    for i in range(n):
        ang = rng.uniform(-np.pi, np.pi)
        unit = np.array([np.cos(ang), np.sin(ang)])
        kind = i % 4
        if kind == 0 and len(present):
            t, h = present[rng.integers(len(present))]
            xy = task["human_pos"][t + 1, h] + rng.uniform(0.0, 1.8) * unit
        elif kind == 1:  # along a box edge: road top, car 2 bottom or building bottom
            xy = (
                np.array(
                    [
                        (rng.uniform(0, 15), 1.9),
                        (rng.uniform(9.9, 11.9), 5.5),
                        (rng.uniform(0, 9.5), 7.0),
                    ][rng.integers(3)]
                )
                + rng.uniform(-0.8, 0.8) * unit
            )
            t = rng.integers(cfg.horizon)
        elif kind == 2:
            xy = task["goal"] + rng.uniform(0.0, 2.5) * unit
            t = rng.integers(cfg.horizon)
        else:
            xy = rng.uniform(lo, hi)
            t = rng.integers(cfg.horizon)
        poses.append([*np.clip(xy, lo, hi), ang])
        steps.append(t)
    return np.asarray(poses), np.asarray(steps)


def _near_threshold(env_np, pose_next, cfg):
    """True when the attempted position lies within MARGIN of any distance threshold."""
    humans, mask = env_np._humans(env_np.t + 1)
    d_h = np.linalg.norm(humans[mask] - pose_next[:2], axis=-1)
    clear = rounded_box_clearance(
        pose_next[:2],
        env_np.task["static_lo"],
        env_np.task["static_hi"],
        env_np.task["static_radius"],
    )
    d_g = np.linalg.norm(pose_next[:2] - env_np.task["goal"])
    thresholds = [
        np.abs(d_h - cfg.eps_dynamic),
        np.abs(d_h - cfg.robot_radius - cfg.human_radius),
        np.abs(clear - cfg.robot_radius),
        np.abs(clear - cfg.robot_radius - cfg.r_safe),
        np.abs([d_g - cfg.goal_radius]),
    ]
    return any(np.any(x < MARGIN) for x in thresholds)


def test_step_matches_numpy_twin(env, tasks):
    """Single steps from many states near people, boxes and the goal, within 1e-5."""
    cfg = env.config
    rng = np.random.default_rng(1)
    step = jax.jit(jax.vmap(env.step, in_axes=(None, 0, 0, None)))
    counts = dict(collision=0, n_dynamic=0, n_static=0, event=0, in_goal=0)
    compared = 0
    for k in range(tasks.num_tasks):
        task = _take(tasks, k)
        twin_task = task_to_numpy(tasks, k)
        poses, steps = _sample_states(rng, twin_task, cfg, 200)
        actions = rng.uniform(-1.0, 1.0, size=(len(poses), 2))
        state = EnvState(pose=jnp.asarray(poses, jnp.float32), t=jnp.asarray(steps, jnp.int32))
        obs, nstate, rew, done, info = step(
            jax.random.PRNGKey(0), state, jnp.asarray(actions, jnp.float32), task
        )
        twin = NumpyNavEnv(cfg, twin_task)
        for i in range(len(poses)):
            twin.set_state(np.asarray(state.pose[i], np.float64), int(steps[i]))
            o, r, d, inf = twin.step(actions[i])
            if _near_threshold(twin, twin.pose, cfg):
                continue
            compared += 1
            np.testing.assert_allclose(np.asarray(nstate.pose[i]), twin.pose, atol=ATOL)
            np.testing.assert_allclose(np.asarray(obs[i]), o, atol=ATOL)
            np.testing.assert_allclose(float(rew[i]), r, atol=1e-4, rtol=1e-6)
            assert bool(done[i]) == d
            for key in counts:
                assert int(getattr(info, key)[i]) == int(inf[key]), key
                counts[key] += int(inf[key]) > 0
    assert compared > 0.95 * tasks.num_tasks * 200
    assert all(c > 10 for c in counts.values()), counts  # every branch was exercised


def test_rollout_matches_numpy_twin(env, tasks):
    """A whole episode towards the goal with noisy steering stays within 1e-4 of the twin."""
    task = _take(tasks, 1)
    twin = NumpyNavEnv(env.config, task_to_numpy(tasks, 1))
    rng = np.random.default_rng(2)
    actions = np.stack([np.full(250, 0.6), rng.uniform(-0.2, 0.2, 250)], axis=-1)
    obs, state = env.reset(jax.random.PRNGKey(0), task)
    np.testing.assert_allclose(np.asarray(obs), twin.reset(), atol=ATOL)
    step = jax.jit(env.step)
    for a in actions:
        obs, state, r, done, info = step(jax.random.PRNGKey(0), state, jnp.asarray(a), task)
        o, r_np, d, inf = twin.step(a)
        np.testing.assert_allclose(np.asarray(state.pose), twin.pose, atol=1e-4)
        np.testing.assert_allclose(float(r), r_np, atol=1e-3, rtol=1e-5)
        assert bool(info.collision) == inf["collision"]
    assert bool(done) and d


def test_step_batches_over_tasks(env, tasks):
    obs, state = jax.vmap(env.reset, in_axes=(None, 0))(jax.random.PRNGKey(0), tasks)
    n = tasks.num_tasks
    obs2, state2, r, _, info = jax.vmap(env.step, in_axes=(None, 0, 0, 0))(
        jax.random.PRNGKey(0), state, jnp.zeros((n, 2)), tasks
    )
    assert obs.shape == (n, 13) and obs2.shape == (n, 13) and r.shape == (n,)
    assert np.all(np.asarray(state2.t) == 1)


def test_trajectory_figure_renders(env, tasks, tmp_path):
    """A PNG with the boxes, pedestrian paths, the robot path and a starred collision."""
    from mpcpearl_jax.envs.sidewalk.plot import plot_sidewalk

    task = _take(tasks, 0)
    traj = env.rollout(jax.random.PRNGKey(0), task, lambda k, o: jnp.array([1.0, 0.0]))
    collisions = np.asarray(traj["collision"]).copy()
    collisions[100] = True  # make sure a star is drawn
    path = tmp_path / "sidewalk.png"
    fig = plot_sidewalk(task, env.config, {"straight": (traj["position"], collisions)}, path)
    ax = fig.axes[0]
    assert path.is_file() and path.stat().st_size > 10_000
    assert len(ax.patches) == 4 + 1  # four boxes and the goal disc
    stars = ax.collections[-1]  # drawn last, one star per collision step
    assert len(stars.get_offsets()) == collisions.sum()
    people = np.asarray(task.human_mask)[::10].sum()
    assert sum(len(c.get_offsets()) for c in ax.collections[:-1]) == people
    assert ax.get_xlim() == env.config.arena_lo[:1] + env.config.arena_hi[:1]
