"""The SQP MPC and the bridge on small scenarios: plan CVaR, collisions, fallbacks, callbacks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.envs import make_env
from mpcpearl_jax.envs.types import EnvState, TaskParams, stack_params
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.mpc import (
    FALLBACK_POLICY,
    NOT_FIRED,
    SOLVED,
    HostSolver,
    MPCBridge,
    MPCConfig,
    RowProblem,
    SQPSolver,
    gp,
    make_gp_mpc_rollout,
    make_mpc_bridge,
    model,
    solver_params,
)
from mpcpearl_jax.mpc.qp_osqp import OSQPSettings

ENV = make_env("restaurant")
T = ENV.config.horizon


def crossing_task(mask_people: bool = False) -> TaskParams:
    """Robot (-4, 0) -> goal (4, 0); person 0 crosses x = 0 upwards when the robot gets there,
    person 1 stands still off the path; one table far from the path."""
    steps = jnp.arange(T + 1, dtype=jnp.float32)
    crosser = jnp.stack([jnp.full(T + 1, 0.3), -2.0 + 0.12 * steps], axis=-1)
    bystander = jnp.broadcast_to(jnp.array([-2.0, 3.0]), (T + 1, 2))
    return TaskParams(
        human_pos=jnp.stack([crosser, bystander], axis=1),
        human_mask=jnp.full((T + 1, 2), not mask_people),
        static_lo=jnp.array([[3.0, 3.5]]),
        static_hi=jnp.array([[3.0, 3.5]]),
        static_radius=jnp.array([0.5]),
        start=jnp.array([-4.0, 0.0, 0.0]),
        goal=jnp.array([4.0, 0.0]),
    )


def run_closed_loop(task: TaskParams, cfg: MPCConfig):
    bridge = make_mpc_bridge(ENV, cfg)
    traj = jax.jit(make_gp_mpc_rollout(ENV, bridge))(jax.random.PRNGKey(0), stack_params([task]))
    return jax.tree_util.tree_map(lambda a: np.asarray(a[0]), traj), bridge


def test_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="MPCConfig.alpha"):
        MPCConfig(alpha=1.5)
    with pytest.raises(ConfigError, match="MPCConfig.gp_mode"):
        MPCConfig(gp_mode="magic")
    with pytest.raises(ConfigError, match="MPCConfig.horizon"):
        MPCConfig(horizon=0)


def test_plan_meets_cvar_with_fresh_samples():
    """eq. (4b): empirical CVaR of the plan's safety loss on 1e4 fresh GP samples."""
    # SQP run to convergence (closed loop: 1-2 QPs per step). With M = 100 the SAA optimum slips
    # between samples (out-of-sample CVaR up to ~0.15 m over delta here); M = 1000 samples shrink
    # that gap, which is what the SAA guarantee promises.
    cfg = MPCConfig(
        gp_mode="fixed",
        gp_lengthscale=0.5,
        gp_signal_std=0.2,
        sqp_iters=50,
        sqp_step_tol=1e-4,
        num_samples=1000,
        qp_tail_samples=100,
    )
    task = crossing_task()
    t = 10  # the crosser is at y = -0.8 heading up; at 5 m/s the robot would meet it at t + 7
    pose = np.array([-1.45, 0.0, 0.0])
    hist = gp.history(task.human_pos[:, 0], jnp.int32(t), cfg.n_gp)
    mean, var = (np.asarray(a, np.float64) for a in gp.predict_person(hist, cfg))
    rng = np.random.default_rng(1)
    draw = lambda m: (
        mean[:, None, None, :]
        + np.sqrt(var)[:, None, None, :]
        * rng.standard_normal(  # noqa: E731
            (cfg.horizon, 1, m, 2)
        )
    )
    prob = RowProblem(
        pose,
        np.asarray(task.goal, float),
        draw(cfg.num_samples),
        np.array([True]),
        np.asarray(task.static_lo, float),
        np.asarray(task.static_hi, float),
        np.asarray(task.static_radius, float),
    )
    params = solver_params(cfg.replace(n_adapt=1), ENV.config, num_static=1)
    solver = SQPSolver(params, OSQPSettings.from_config(cfg))
    res = solver.solve(prob, np.column_stack([np.full(10, 5.0), np.zeros(10)]))
    assert res.ok, res.reason
    assert var[-1].max() > 0.01  # the prediction is genuinely uncertain
    fresh = draw(10_000)[:, 0]  # [K, 1e4, 2]
    loss = params.eps_dynamic - np.linalg.norm(res.poses[1:, None, :2] - fresh, axis=-1)
    cvar = model.saa_cvar(loss, cfg.alpha)
    assert np.all(cvar <= cfg.delta_cvar + 0.05), cvar
    # the naive straight plan at full speed would violate the constraint
    naive = model.rollout(pose, np.column_stack([np.full(10, 5.0), np.zeros(10)]), ENV.config.dt)
    naive_loss = params.eps_dynamic - np.linalg.norm(naive[1:, None, :2] - fresh, axis=-1)
    assert model.saa_cvar(naive_loss, cfg.alpha).max() > cfg.delta_cvar + 0.3


def test_crossing_person_closed_loop_has_no_collision_and_reaches_goal():
    crosser = np.asarray(crossing_task().human_pos[1:, 0])
    straight = np.column_stack([-4.0 + 0.25 * np.arange(1, T + 1), np.zeros(T)])  # 5 m/s
    assert np.linalg.norm(straight - crosser, axis=-1).min() < 0.5  # driving straight collides
    traj, bridge = run_closed_loop(crossing_task(), MPCConfig())
    d = np.linalg.norm(traj["position"][1:] - crosser, axis=-1)
    assert not traj["collision"].any()
    assert d.min() > ENV.config.robot_radius + ENV.config.human_radius
    assert traj["in_goal"].any()
    assert bridge.stats()["calls"] == T


def test_no_people_reaches_goal_and_masked_people_do_not_constrain():
    # masked people stand on the straight path: they must be ignored
    task = crossing_task(mask_people=True)
    task = task.replace(human_pos=task.human_pos.at[:, :, 1].set(0.0))
    traj, bridge = run_closed_loop(task, MPCConfig())
    assert traj["in_goal"].any() and not traj["collision"].any()
    assert np.all(traj["position"][1:, 1] > -0.3) and np.all(traj["position"][1:, 1] < 0.3)
    assert bridge.stats()["status"].get("solved", 0) >= T - 2


def test_start_inside_table_margin_gives_counted_fallback():
    task = crossing_task()
    task = task.replace(start=jnp.array([2.4, 3.5, np.pi]))  # 0.6 m from a table centre (need 1.0)
    bridge = make_mpc_bridge(ENV, MPCConfig())
    params = stack_params([task])
    state = EnvState(pose=params.start, t=jnp.zeros(1, jnp.int32))
    policy = jnp.array([[0.25, -0.5]])
    _, act, used, status = jax.jit(bridge.step)(
        bridge.init(1), jax.random.PRNGKey(0), jnp.array([True]), state, params, policy
    )
    assert int(status[0]) == FALLBACK_POLICY and not bool(used[0])
    np.testing.assert_allclose(act, policy)
    stats = bridge.stats()
    assert stats["fallbacks"] == 1 and stats["reasons"] == {"unsafe": 1}


class RecordingHost(HostSolver):
    """Records the MPC action of every merged row to check the merge."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.log = []

    def merge_row(self, mem, b, t, res):
        code, act = super().merge_row(mem, b, t, res)
        self.log.append((int(t), int(b), code, None if act is None else act.copy()))
        return code, act


def test_callback_runs_only_on_steps_with_a_fire_and_merges_actions():
    tasks = stack_params([crossing_task(), crossing_task(), crossing_task()])
    batch, steps = 3, 12
    rng = np.random.default_rng(0)
    fire_tb = rng.random((steps, batch)) < 0.3
    fire_tb[[2, 5, 9]] = False  # some steps with no fire at all
    fire_tb[0] = [True, False, True]
    policy_tb = rng.uniform(-1, 1, (steps, batch, 2)).astype(np.float32)
    host = RecordingHost(ENV.config, MPCConfig())
    bridge = MPCBridge(ENV, MPCConfig(), host=host)

    @jax.jit
    def run(key):
        _, s0 = jax.vmap(ENV.reset)(jax.random.split(key, batch), tasks)
        carry = bridge.init(batch)

        def body(state, xs):
            k, fire, pol = xs
            _, act, used, status = bridge.step(carry, k, fire, state, tasks, pol)
            _, ns, _, _, _ = jax.vmap(ENV.step)(jax.random.split(k, batch), state, act, tasks)
            return ns, (act, used, status)

        keys = jax.random.split(key, steps)
        return jax.lax.scan(body, s0, (keys, jnp.asarray(fire_tb), jnp.asarray(policy_tb)))[1]

    act, used, status = (np.asarray(a) for a in run(jax.random.PRNGKey(0)))
    stats = bridge.stats()
    assert stats["calls"] == int(fire_tb.any(axis=1).sum())
    assert stats["rows_solved"] == int(fire_tb.sum())
    np.testing.assert_array_equal(act[~fire_tb], policy_tb[~fire_tb])
    assert np.all(status[~fire_tb] == NOT_FIRED) and np.all(status[fire_tb] != NOT_FIRED)
    np.testing.assert_array_equal(used, status == SOLVED)
    assert len(host.log) == fire_tb.sum()
    for t, b, code, mpc_u in host.log:  # the MPC's physical input, or None: the policy acts
        assert fire_tb[t, b] and code == status[t, b]
        if mpc_u is None:
            np.testing.assert_array_equal(act[t, b], policy_tb[t, b])
        else:  # the env's action mapping of the MPC's (v, delta)
            want = [2.0 * mpc_u[0] / ENV.config.v_max - 1.0, mpc_u[1] / (np.pi / 2)]
            np.testing.assert_allclose(act[t, b], want, atol=1e-6)
    assert (status == SOLVED).sum() > 0


def test_unsafe_recovery_uses_the_least_violating_move_instead_of_falling_back():
    from mpcpearl_jax.envs.types import EnvState, stack_params
    from mpcpearl_jax.mpc import SOLVED, MPCConfig, make_mpc_bridge

    task = crossing_task().replace(start=jnp.array([2.4, 3.5, np.pi]))  # 0.6 m from a table
    params = stack_params([task])
    state = EnvState(pose=params.start, t=jnp.zeros(1, jnp.int32))
    policy = jnp.array([[0.25, -0.5]])
    bridge = make_mpc_bridge(ENV, MPCConfig(unsafe_recovery=True))
    _, act, used, status = jax.jit(bridge.step)(
        bridge.init(1), jax.random.PRNGKey(0), jnp.array([True]), state, params, policy
    )
    assert int(status[0]) == SOLVED and bool(used[0])
    assert bridge.stats()["reasons"] == {"least_violation": 1}
    # the executed move does not bring the robot closer to the table than standing still
    _, nstate, _, _, _ = ENV.step(jax.random.PRNGKey(0), EnvState(params.start[0], 0), act[0], task)
    before = float(jnp.linalg.norm(params.start[0, :2] - jnp.array([3.0, 3.5])))
    after = float(jnp.linalg.norm(nstate.pose[:2] - jnp.array([3.0, 3.5])))
    assert after >= before - 1e-6
