"""The JAX navigation step against the independent NumPy twin (method §1-2), within 1e-5."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.envs import EnvState, NumpyNavEnv, make_env, make_tasks, task_to_numpy
from mpcpearl_jax.envs import numpy_ref as ref

ATOL = 1e-5
NUM_RANDOM = 3000
MARGIN = 1e-4  # samples this close to a threshold are ambiguous between float32 and float64


def _take(params, i):
    return jax.tree_util.tree_map(lambda x: x[i], params)


def _with_boxes_and_absent_people(params):
    """Turn two tables into plain/rounded boxes and hide some people part of the time.

    Exercises the generic rounded-box distance and the presence mask on restaurant geometry.
    """
    lo = np.array(params.static_lo)
    hi = np.array(params.static_hi)
    rad = np.array(params.static_radius)
    lo[..., 0, :] -= np.array([0.6, 0.3])
    hi[..., 0, :] += np.array([0.4, 0.2])
    rad[..., 0] = 0.0
    lo[..., 1, :] -= 0.3
    hi[..., 1, :] += np.array([0.5, 0.1])
    rad[..., 1] = 0.2
    mask = np.array(params.human_mask)
    mask[..., :30, 0] = False
    mask[..., 50:, 3] = False
    mask[..., :, 5] = False
    return params.replace(
        static_lo=jnp.asarray(lo),
        static_hi=jnp.asarray(hi),
        static_radius=jnp.asarray(rad),
        human_mask=jnp.asarray(mask),
    )


@pytest.fixture(scope="module", params=["restaurant", "r_safe_0.125", "boxes_and_mask"])
def setup(request):
    """(env, stacked params) for three variants of the restaurant family."""
    env = make_env("restaurant")
    tasks = make_tasks("restaurant", "train", seed=0)
    tasks = _take(tasks, np.arange(0, 120, 6))  # 20 tasks: every configuration, many behaviours
    if request.param == "r_safe_0.125":
        env = make_env("restaurant", r_safe=0.125)
    elif request.param == "boxes_and_mask":
        tasks = _with_boxes_and_absent_people(tasks)
    return env, tasks


def _sample_pose(rng, kind, task, t, cfg):
    """A pose [3] of the given kind near something interesting at step t + 1."""
    lo = np.asarray(cfg.arena_lo) + cfg.robot_radius
    hi = np.asarray(cfg.arena_hi) - cfg.robot_radius
    ang = rng.uniform(-np.pi, np.pi)
    unit = np.array([np.cos(ang), np.sin(ang)])
    if kind == "uniform":
        xy = rng.uniform(lo, hi)
    elif kind == "table":
        s = rng.integers(task["static_lo"].shape[0])
        centre = 0.5 * (task["static_lo"][s] + task["static_hi"][s])
        xy = centre + rng.uniform(0.3, 1.6) * unit
    elif kind == "human":
        xy = task["human_pos"][t + 1, rng.integers(task["human_pos"].shape[1])]
        xy = xy + rng.uniform(0.0, 1.6) * unit
    elif kind == "goal":
        xy = task["goal"] + rng.uniform(0.0, 0.9) * unit
    else:  # wall
        xy = rng.uniform(lo, hi)
        axis = rng.integers(2)
        xy[axis] = rng.choice([lo[axis], hi[axis]]) + rng.uniform(-0.2, 0.2)
    return np.array([*np.clip(xy, lo, hi), rng.uniform(-np.pi, np.pi)])


def _sample_action(rng):
    """Mostly inside [-1, 1]^2, some far outside, some exactly on the bounds."""
    u = rng.random()
    if u < 0.6:
        return rng.uniform(-1.0, 1.0, 2)
    if u < 0.9:
        return rng.uniform(-3.0, 3.0, 2)
    return rng.choice([-1.0, 1.0], 2)


def _margin(cfg, task, pose, t, action):
    """Smallest distance of any thresholded quantity of this step to its threshold."""
    goal = task["goal"]
    v, delta = ref.normalized_to_physical(action, cfg.v_max)
    d_goal = math.hypot(pose[0] - goal[0], pose[1] - goal[1])
    gaps = [abs(d_goal - cfg.robot_radius), abs(d_goal - cfg.goal_event_radius)]
    if d_goal <= cfg.robot_radius:
        v = 0.0
    x, y, _ = ref.bicycle(*pose, v, delta, cfg.dt, cfg.wheelbase)
    p = np.clip([x, y], np.add(cfg.arena_lo, cfg.robot_radius), np.subtract(cfg.arena_hi, 0.25))
    eps_d = cfg.robot_radius + cfg.human_radius + cfg.r_safe
    for q, tt, thresholds in (
        (p, t + 1, (eps_d, cfg.robot_radius + cfg.human_radius)),
        (pose[:2], t, (cfg.collision_event_factor * eps_d,)),
    ):
        dh = np.linalg.norm(task["human_pos"][tt] - q, axis=-1)
        gaps += [abs(d - th) for d in dh for th in thresholds]
    clear = ref.rounded_box_clearance(
        p, task["static_lo"], task["static_hi"], task["static_radius"]
    )
    gaps += [abs(c - th) for c in clear for th in (cfg.robot_radius, cfg.robot_radius + cfg.r_safe)]
    for q in (p, pose[:2]):
        gaps.append(abs(math.hypot(q[0] - goal[0], q[1] - goal[1]) - cfg.goal_radius))
    return min(gaps)


def _angle_diff(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi)


def test_random_states_and_actions(setup):
    env, tasks = setup
    cfg = env.config
    rng = np.random.default_rng(0)
    n_tasks = tasks.num_tasks
    kinds = ["uniform", "table", "human", "goal", "wall"]
    np_tasks = [task_to_numpy(tasks, i) for i in range(n_tasks)]
    rows = []
    while len(rows) < NUM_RANDOM:
        i = int(rng.integers(n_tasks))
        t = int(rng.integers(cfg.horizon))
        pose = _sample_pose(rng, kinds[len(rows) % len(kinds)], np_tasks[i], t, cfg)
        pose = pose.astype(np.float32).astype(np.float64)
        action = _sample_action(rng).astype(np.float32).astype(np.float64)
        if _margin(cfg, np_tasks[i], pose, t, action) > MARGIN:
            rows.append((i, t, pose, action))
    idx = np.array([r[0] for r in rows])
    state = EnvState(
        pose=jnp.asarray(np.array([r[2] for r in rows]), jnp.float32),
        t=jnp.asarray(np.array([r[1] for r in rows]), jnp.int32),
    )
    actions = jnp.asarray(np.array([r[3] for r in rows]), jnp.float32)
    params = _take(tasks, idx)
    step = jax.jit(jax.vmap(env.step, in_axes=(None, 0, 0, 0)))
    obs, nstate, rew, done, info = jax.device_get(
        step(jax.random.PRNGKey(0), state, actions, params)
    )

    exp = {k: [] for k in ("obs", "pose", "rew", "done", "col", "goal", "nd", "ns", "ev")}
    for i, t, pose, action in rows:
        twin = NumpyNavEnv(cfg, np_tasks[i])
        twin.set_state(pose, t)
        o, r, d, inf = twin.step(action)
        exp["obs"].append(o)
        exp["pose"].append(twin.pose)
        exp["rew"].append(r)
        exp["done"].append(d)
        exp["col"].append(inf["collision"])
        exp["goal"].append(inf["in_goal"])
        exp["nd"].append(inf["n_dynamic"])
        exp["ns"].append(inf["n_static"])
        exp["ev"].append(inf["event"])
    exp = {k: np.array(v) for k, v in exp.items()}

    np.testing.assert_array_equal(info.collision, exp["col"])
    np.testing.assert_array_equal(info.n_dynamic, exp["nd"])
    np.testing.assert_array_equal(info.n_static, exp["ns"])
    np.testing.assert_array_equal(info.in_goal, exp["goal"])
    np.testing.assert_array_equal(info.event, exp["ev"])
    np.testing.assert_array_equal(done, exp["done"])
    np.testing.assert_allclose(nstate.pose[:, :2], exp["pose"][:, :2], rtol=0, atol=ATOL)
    assert np.max(_angle_diff(nstate.pose[:, 2], exp["pose"][:, 2])) < ATOL
    np.testing.assert_allclose(info.position, exp["pose"][:, :2], rtol=0, atol=ATOL)
    np.testing.assert_allclose(rew, exp["rew"], rtol=1e-6, atol=ATOL)
    theta_col = 2  # theta / pi may sit at -1 vs +1 after wrapping; compare as angles
    keep = np.ones(obs.shape[1], bool)
    keep[theta_col] = False
    np.testing.assert_allclose(obs[:, keep], exp["obs"][:, keep], rtol=0, atol=ATOL)
    assert np.max(_angle_diff(np.pi * obs[:, theta_col], np.pi * exp["obs"][:, theta_col])) < 1e-4

    # The sample must exercise every branch, or the comparison proves little.
    start = np.array([r[2] for r in rows])
    goal = np.asarray(params.goal)
    parked = np.linalg.norm(start[:, :2] - goal, axis=-1) <= cfg.robot_radius
    clipped_lo = np.isclose(exp["pose"][:, :2], np.add(cfg.arena_lo, cfg.robot_radius))
    assert exp["col"].mean() > 0.05 and (~exp["col"]).mean() > 0.5
    assert (exp["nd"] > 0).sum() > 50 and (exp["ns"] > 0).sum() > 50
    assert parked.sum() > 20 and exp["goal"].sum() > 50
    assert (clipped_lo.any(axis=1) & ~exp["col"]).sum() > 20
    assert exp["ev"].mean() > 0.1


def _go_to_goal(rng, pose, goal):
    """A noisy steer-to-goal action in normalized units (sometimes outside [-1, 1])."""
    heading = math.atan2(goal[1] - pose[1], goal[0] - pose[0])
    err = ref.wrap_to_pi(heading - pose[2])
    a = np.array([0.2, np.clip(2.0 * err / np.pi, -1, 1)]) + rng.normal(0, 0.6, 2)
    return a.astype(np.float32).astype(np.float64)


@pytest.mark.parametrize("task_index", [0, 7, 13])
def test_full_episodes_step_by_step(setup, task_index):
    env, tasks = setup
    cfg = env.config
    params = _take(tasks, task_index)
    twin = NumpyNavEnv(cfg, task_to_numpy(params))
    step = jax.jit(env.step)
    rng = np.random.default_rng(task_index)
    obs, state = env.reset(jax.random.PRNGKey(0), params)
    obs_np = twin.reset()
    np.testing.assert_allclose(obs, obs_np, atol=ATOL)
    seen_goal = seen_collision = False
    for t in range(cfg.horizon):
        a = _go_to_goal(rng, twin.pose, twin.task["goal"]) if t % 3 else rng.uniform(-1.5, 1.5, 2)
        obs, state, r, done, info = step(jax.random.PRNGKey(t), state, jnp.asarray(a), params)
        obs_np, r_np, done_np, info_np = twin.step(a)
        np.testing.assert_allclose(state.pose[:2], twin.pose[:2], atol=ATOL, err_msg=f"t={t}")
        assert _angle_diff(state.pose[2], twin.pose[2]) < ATOL, t
        np.testing.assert_allclose(float(r), r_np, rtol=1e-6, atol=ATOL, err_msg=f"t={t}")
        assert bool(info.collision) == info_np["collision"], t
        assert bool(info.in_goal) == info_np["in_goal"], t
        assert int(info.n_dynamic) == info_np["n_dynamic"], t
        assert int(info.n_static) == info_np["n_static"], t
        assert bool(info.event) == info_np["event"], t
        assert bool(done) == done_np, t
        seen_goal |= info_np["in_goal"]
        seen_collision |= info_np["collision"]
    assert done_np and state.t == cfg.horizon
    assert seen_goal or seen_collision  # the policy reaches the goal or at least hits something


def test_parking_and_collision_semantics_hand_case():
    """Small hand-built cases: parked robots do not move; a blocked move keeps the whole pose."""
    env = make_env("restaurant")
    cfg = env.config
    task = task_to_numpy(_take(make_tasks("restaurant", "test"), 0))
    twin = NumpyNavEnv(cfg, task)
    goal = task["goal"]
    twin.set_state([goal[0] + 0.1, goal[1], 0.3], 5)
    _, r, _, info = twin.step(np.array([1.0, 0.5]))
    np.testing.assert_allclose(twin.pose, [goal[0] + 0.1, goal[1], 0.3])
    delta = 0.5 * np.pi / 2
    expected = -(0.01 + 0.2 * delta**2) / 25 + 10.0
    assert info["in_goal"] and not info["collision"]
    assert r == pytest.approx(expected - 20 * (info["n_dynamic"] + info["n_static"]))

    centre = 0.5 * (task["static_lo"][0] + task["static_hi"][0])
    twin.set_state([centre[0] - 0.8, centre[1], 0.0], 0)  # heading straight at the table
    _, r, _, info = twin.step(np.array([1.0, 0.0]))  # 0.35 m forward: 0.45 from the centre
    assert info["collision"] and info["n_static"] >= 1
    np.testing.assert_allclose(twin.pose, [centre[0] - 0.8, centre[1], 0.0])
    assert r <= -20.0


def test_task_to_numpy_errors():
    tasks = make_tasks("restaurant", "test")
    with pytest.raises(ValueError, match="pass an index"):
        task_to_numpy(tasks)
    with pytest.raises(ValueError, match="not stacked"):
        task_to_numpy(_take(tasks, 0), 0)
    twin = NumpyNavEnv(make_env("restaurant").config, task_to_numpy(tasks, 1))
    twin.reset()
    with pytest.raises(ValueError, match="shape"):
        twin.step(np.zeros(3))


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_full_steering_is_the_limit_of_near_full_steering(sign):
    """delta = +-pi/2 (where tan is infinite) continues the motion of |delta| slightly smaller."""
    from mpcpearl_jax.envs.dynamics import bicycle_step, to_physical

    pose = jnp.array([0.0, 0.0, 0.3], jnp.float32)
    u_full = to_physical(jnp.array([1.0, sign]), 7.0)
    u_near = jnp.array([7.0, sign * (np.pi / 2 - 1e-3)], jnp.float32)
    full = np.asarray(bicycle_step(pose, u_full, 0.05, 0.5))
    near = np.asarray(bicycle_step(pose, u_near, 0.05, 0.5))
    np.testing.assert_allclose(full, near, atol=2e-3)
    assert sign * (full[2] - 0.3) == pytest.approx(0.05 * 7.0 * 2 / 0.5, rel=1e-5)  # v / l_r
    assert sign * (full[1] - 0.0) > 0.3  # full left steering slides left, full right slides right
    twin = ref.bicycle(0.0, 0.0, 0.3, 7.0, sign * np.pi / 2, 0.05, 0.5)
    np.testing.assert_allclose(twin, full, atol=ATOL)
