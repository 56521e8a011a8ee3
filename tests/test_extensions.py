"""Extensions beyond the paper (docs/extensions.md): MPC warm start, MPC buffer with masked
inserts, Q-filtered behaviour cloning, LayerNorm critics, least-violation MPC moves. Each is off by
default and in the `paper` preset."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.config import ExperimentConfig, PearlConfig, TrainConfig, preset
from mpcpearl_jax.envs.types import ConfigError
from mpcpearl_jax.pearl import Transitions, buffers, losses
from mpcpearl_jax.pearl.networks import Networks

OBS, A = 5, 2


def _transitions(k, n, start=0.0):
    r = jnp.arange(k * n, dtype=jnp.float32).reshape(k, n) + start
    return Transitions(
        jnp.repeat(r[..., None], OBS, -1),
        jnp.repeat(r[..., None], A, -1),
        r,
        jnp.repeat(r[..., None], OBS, -1),
        jnp.zeros((k, n)),
    )


def _insert_masked_ref(store, size, ptr, cap, task_ids, reward, mask):
    """NumPy reference: append the kept rewards of each task to its ring buffer, in order."""
    store, size, ptr = store.copy(), size.copy(), ptr.copy()
    for i, t in enumerate(task_ids):
        for v in reward[i][mask[i]]:
            store[t, ptr[t]] = v
            ptr[t] = (ptr[t] + 1) % cap
            size[t] = min(size[t] + 1, cap)
    return store, size, ptr


def test_insert_masked_matches_numpy_ring_buffer():
    rng = np.random.default_rng(0)
    cap, n_tasks, n = 7, 4, 5
    buf = buffers.init_buffer(n_tasks, cap, OBS, A)
    store = np.zeros((n_tasks, cap), np.float32)
    size = np.zeros(n_tasks, np.int64)
    ptr = np.zeros(n_tasks, np.int64)
    for step in range(6):  # wraps around several times
        ids = rng.choice(n_tasks, 2, replace=False)
        data = _transitions(2, n, start=100.0 * step)
        mask = rng.uniform(size=(2, n)) < 0.6
        buf = jax.jit(buffers.insert_masked)(buf, jnp.asarray(ids), data, jnp.asarray(mask))
        store, size, ptr = _insert_masked_ref(
            store, size, ptr, cap, ids, np.asarray(data.reward), mask
        )
        np.testing.assert_array_equal(np.asarray(buf.size), size)
        np.testing.assert_array_equal(np.asarray(buf.ptr), ptr)
        for t in range(n_tasks):  # only the valid slots are defined
            np.testing.assert_array_equal(
                np.asarray(buf.data.reward)[t, : size[t]], store[t, : size[t]]
            )
            np.testing.assert_array_equal(
                np.asarray(buf.data.obs)[t, : size[t], 0], store[t, : size[t]]
            )


def test_insert_masked_all_true_equals_insert():
    buf = buffers.init_buffer(3, 6, OBS, A)
    data = _transitions(2, 4)
    ids = jnp.array([2, 0])
    a = buffers.insert(buffers.insert(buf, ids, data), ids, data)
    m = jnp.ones((2, 4), bool)
    b = buffers.insert_masked(buffers.insert_masked(buf, ids, data, m), ids, data, m)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _bc_setup(bc_weight):
    cfg = PearlConfig(hidden=(16, 16), encoder_hidden=(8,), latent_dim=2, bc_weight=bc_weight)
    nets = Networks(cfg, OBS, A)
    params = nets.init(jax.random.PRNGKey(0))
    k = jax.random.split(jax.random.PRNGKey(1), 3)
    obs = jax.random.normal(k[0], (2, 8, OBS))
    z = jax.random.normal(k[1], (2, 8, 2))
    demo_action = jnp.tanh(jax.random.normal(k[2], (2, 8, A)))
    return cfg, nets, params, obs, z, demo_action


def _policy_loss(cfg, nets, params, obs, z, demo_action, demo_mask, q_params=None):
    return losses.policy_loss(
        params["policy"],
        nets,
        params["q"] if q_params is None else q_params,
        obs,
        z,
        jax.random.PRNGKey(3),
        cfg.policy_mean_reg,
        cfg.policy_std_reg,
        demo_action,
        demo_mask,
        cfg.bc_weight,
    )


def test_bc_term_is_zero_when_off_or_without_demo_rows():
    cfg0, nets, params, obs, z, demo = _bc_setup(0.0)
    base, _ = _policy_loss(cfg0, nets, params, obs, z, demo, jnp.ones((2, 8)))
    cfg1 = dataclasses.replace(cfg0, bc_weight=1.0)
    none, aux = _policy_loss(cfg1, nets, params, obs, z, demo, jnp.zeros((2, 8)))
    np.testing.assert_allclose(float(base), float(none), rtol=1e-6)
    assert float(aux["bc_kept"]) == 0.0


def test_bc_term_matches_hand_computation_and_q_filter():
    cfg, nets, params, obs, z, demo = _bc_setup(0.5)
    mask = jnp.zeros((2, 8)).at[:, :3].set(1.0)
    base, _ = _policy_loss(
        dataclasses.replace(cfg, bc_weight=0.0), nets, params, obs, z, demo, mask
    )
    loss, aux = _policy_loss(cfg, nets, params, obs, z, demo, mask)
    mean, log_std = nets.policy_out(params["policy"], obs, z)
    det = jnp.tanh(mean)
    q_det = jnp.minimum(*nets.q_values(params["q"], obs, det, z))
    q_demo = jnp.minimum(*nets.q_values(params["q"], obs, demo, z))
    from mpcpearl_jax.pearl.networks import tanh_gaussian

    a, _ = tanh_gaussian(mean, log_std).sample_and_log_prob(seed=jax.random.PRNGKey(3))
    q_scale = jnp.mean(jnp.abs(jnp.minimum(*nets.q_values(params["q"], obs, a, z))))
    keep = mask * (q_demo > q_det)
    want = 0.5 * q_scale * jnp.sum(keep * jnp.sum((det - demo) ** 2, -1)) / jnp.sum(mask)
    np.testing.assert_allclose(float(loss - base), float(want), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(float(aux["bc_kept"]), float(jnp.sum(keep) / 6.0), rtol=1e-6)
    # a critic that prefers the demo everywhere keeps every demo row; one that never does, none
    prefer = jax.tree_util.tree_map(jnp.zeros_like, params["q"])
    _, aux0 = _policy_loss(cfg, nets, params, obs, z, demo, mask, prefer)
    assert float(aux0["bc_kept"]) == 0.0  # equal Q: the strict filter keeps nothing


def test_bc_gradient_pulls_policy_mean_towards_mpc_action():
    cfg, nets, params, obs, z, demo = _bc_setup(50.0)
    mask = jnp.ones((2, 8))

    # a Q that ranks the MPC action first: Q(s, a) = -|a - a_mpc|^2 through a stub network
    def q_prefers_demo(p, o, a, zz):
        q = -jnp.sum((a - demo) ** 2, -1) * 10.0
        return q, q

    stub = type("N", (), {})()
    stub.policy_out = nets.policy_out
    stub.q_values = q_prefers_demo

    def bc_only(pp):
        full, _ = losses.policy_loss(
            pp, stub, None, obs, z, jax.random.PRNGKey(3), 0.0, 0.0, demo, mask, cfg.bc_weight
        )
        return full

    g = jax.grad(bc_only)(params["policy"])
    step = jax.tree_util.tree_map(lambda p, gg: p - 1e-3 * gg, params["policy"], g)
    before = jnp.mean((jnp.tanh(nets.policy_out(params["policy"], obs, z)[0]) - demo) ** 2)
    after = jnp.mean((jnp.tanh(nets.policy_out(step, obs, z)[0]) - demo) ** 2)
    assert float(after) < float(before)


def test_layer_norm_adds_scale_and_bias_to_critics_only():
    cfg = PearlConfig(hidden=(8, 8), encoder_hidden=(4,), latent_dim=2, layer_norm=True)
    p = Networks(cfg, OBS, A).init(jax.random.PRNGKey(0))
    names = lambda tree: {  # noqa: E731
        "/".join(str(getattr(k, "key", k)) for k in path)
        for path, _ in jax.tree_util.tree_flatten_with_path(tree)[0]
    }
    assert any("LayerNorm" in n for n in names(p["q"]))
    assert any("LayerNorm" in n for n in names(p["v"]))
    assert not any("LayerNorm" in n for n in names(p["policy"]))
    off = Networks(dataclasses.replace(cfg, layer_norm=False), OBS, A).init(jax.random.PRNGKey(0))
    assert not any("LayerNorm" in n for n in names(off["q"]))


def test_demo_share_schedule():
    tc = TrainConfig(mpc_demo_share=0.8, mpc_demo_iterations=10)
    assert tc.demo_share(0) == pytest.approx(0.8)
    assert tc.demo_share(5) == pytest.approx(0.4)
    assert tc.demo_share(10) == 0.0 and tc.demo_share(50) == 0.0
    assert TrainConfig().demo_share(0) == 0.0
    # eps = 0 is PEARL: no MPC, so no warm start either
    pearl = TrainConfig(eps=0.0, mpc_demo_share=0.5, mpc_demo_iterations=3)
    assert not pearl.uses_mpc and pearl.demo_share(0) == 0.0


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: TrainConfig(mpc_demo_share=1.5), "mpc_demo_share"),
        (lambda: TrainConfig(mpc_buffer_fraction=1.0), "mpc_buffer_fraction"),
        (lambda: TrainConfig(mpc_demo_iterations=-1), "mpc_demo_iterations"),
        (lambda: PearlConfig(bc_weight=-1.0), "bc_weight"),
        (lambda: PearlConfig(layer_norm="False"), "layer_norm"),
        (
            lambda: ExperimentConfig(pearl=PearlConfig(bc_weight=1.0)),
            "bc_weight",
        ),
        (lambda: TrainConfig(mpc_demo_step_prob=-0.1), "mpc_demo_step_prob"),
        (lambda: TrainConfig(explore_start_share=1.0), "explore_start_share"),
        (lambda: TrainConfig(explore_start_share=-0.1), "explore_start_share"),
        (lambda: TrainConfig(explore_start_share=True), "explore_start_share"),
        (
            lambda: TrainConfig(explore_start_share=0.5, posterior_episodes=0),
            "explore_start_share",
        ),
        (lambda: PearlConfig(bc_q_filter=1), "bc_q_filter"),
    ],
)
def test_invalid_extension_settings_name_the_field(make, field):
    with pytest.raises(ConfigError, match=field):
        make()


@pytest.mark.parametrize("name", ["paper", "cpu-paper", "smoke"])
def test_paper_presets_have_every_extension_off(name):
    cfg = preset(name)
    if name == "paper":
        assert cfg.train == TrainConfig() and cfg.pearl == PearlConfig()
    assert cfg.train.mpc_demo_share == 0 and cfg.train.mpc_buffer_fraction == 0
    assert cfg.train.mpc_demo_step_prob == 1.0
    assert cfg.pearl.bc_weight == 0 and not cfg.pearl.layer_norm
    assert not cfg.pearl.auto_entropy and cfg.pearl.target_entropy is None
    assert not cfg.mpc.unsafe_recovery and cfg.train.explore_start_share == 0
    assert cfg.train.crowd_delay_max == 0
    for field in (
        "observe_velocity",
        "observe_relative",
        "sensing_radius",
        "observe_time",
        "observe_sorted",
    ):
        assert not cfg.env_overrides.get(field), field
    from mpcpearl_jax.envs import make_env

    assert not make_env(cfg.env, **cfg.env_overrides).config.observe_sorted


def test_cpu_presets_differ_only_in_the_extensions():
    ext, paper = preset("cpu"), preset("cpu-paper")
    assert ext.train.mpc_demo_share > 0 and ext.pearl.bc_weight > 0 and ext.pearl.layer_norm
    assert ext.mpc.unsafe_recovery
    same = dataclasses.replace(
        ext.train,
        mpc_demo_share=0.0,
        mpc_demo_iterations=0,
        mpc_demo_step_prob=1.0,
        mpc_buffer_fraction=0.0,
    )
    assert same == paper.train
    assert ext.pearl.replace(bc_weight=0.0, bc_q_filter=True, layer_norm=False) == paper.pearl


@pytest.mark.parametrize(
    "name, eps, algo, folder",
    [
        ("cpu-explore", "0.2", "pearl", "mpc-pearl-eps0.2"),
        ("cpu-explore", "0", "pearl", "pearl"),
        ("cpu-explore", "0.2", "sac", "mpc-sac"),
        ("cpu-robust", "0.2", "pearl", "ablation/crowd-delay20-30min"),
        ("cpu-auto", "0.2", "pearl", "ablation/auto-entropy-24min"),
        ("cpu-auto", "0", "pearl", "ablation/pearl-auto-entropy-24min"),
        ("cpu-auto", "0.2", "sac", "ablation/mpc-sac-auto-entropy-24min"),
        ("cpu-tuned", "0.2", "pearl", "ablation/extended-60min"),
        ("cpu-tuned", "0", "pearl", "ablation/pearl-tuned-60min"),
        ("cpu-tuned", "0.2", "sac", "ablation/mpc-sac-tuned-60min"),
    ],
)
def test_presets_build_the_committed_restaurant_runs(tmp_path, capsys, name, eps, algo, folder):
    """`--preset P --eps E` builds exactly the committed run's config.json (the run wrote the
    iterations it finished), so one short command reproduces it; the sidewalk, which cannot
    re-draw its crowds, is refused before anything is written."""
    import json
    from pathlib import Path

    from experiments import learning
    from experiments.common import ENV_EXTRAS, build_config

    args = learning.parse_args(["--preset", name, "--eps", eps, "--algo", algo, "--minutes", "60"])
    cfg = build_config(args, "restaurant", **ENV_EXTRAS["restaurant"])
    head = Path(__file__).parents[1] / "results/restaurant" / folder / "config.json"
    ref = ExperimentConfig.from_dict(json.loads(head.read_text()))
    assert cfg == ref.replace(train=dataclasses.replace(ref.train, iterations=cfg.train.iterations))
    argv = ["--env", "sidewalk", "--preset", name, "--eps", "0.2", "--minutes", "1"]
    out = tmp_path / "run"
    assert learning.main([*argv, "--out", str(out)]) == 2
    assert "train.redraw_behaviours" in capsys.readouterr().err and not out.exists()


def test_tuned_presets_differ_from_cpu_only_where_documented():
    tuned, cpu, explore = preset("cpu-tuned"), preset("cpu"), preset("cpu-explore")
    assert tuned.mpc == cpu.mpc and tuned.pearl.replace(bc_weight=cpu.pearl.bc_weight) == cpu.pearl
    assert explore.pearl == tuned.pearl.replace(bc_weight=0.0)
    assert explore.env_overrides == tuned.env_overrides and explore.mpc == tuned.mpc
    changed = {
        k: v for k, v in explore.train.__dict__.items() if tuned.train.__dict__[k] != v
    }  # the MPC-based extensions off, exploring starts on
    assert changed == {
        "mpc_demo_share": 0.0,
        "mpc_demo_iterations": 0,
        "mpc_buffer_fraction": 0.0,
        "explore_start_share": 0.5,
    }
    default = preset("default")
    assert default.train.explore_start_share == 0.5 and default.train.mpc_demo_share == 0
    assert default.pearl.hidden == (64, 64) and default.pearl.meta_batch == 4
    assert default.pearl == explore.pearl.replace(
        hidden=(64, 64), encoder_hidden=(64, 64), meta_batch=4, auto_entropy=True
    )
    assert default.env_overrides == tuned.env_overrides


def test_default_preset_keeps_the_sidewalk_crowd():
    """The main command's preset re-draws crowds on the restaurant and leaves the sidewalk's
    recorded crowd alone (instead of refusing it, as an explicit preset is)."""
    from experiments.common import ENV_EXTRAS, build_config, parser

    for env, redraw in (("restaurant", True), ("sidewalk", False)):
        cfg = build_config(parser(env).parse_args([]), env, **ENV_EXTRAS[env])
        assert cfg.train.redraw_behaviours is redraw and cfg.train.explore_start_share == 0.5


def test_unsafe_recovery_uses_the_least_violating_move_instead_of_falling_back():
    from mpcpearl_jax.envs.types import EnvState, stack_params
    from mpcpearl_jax.mpc import SOLVED, MPCConfig, make_mpc_bridge
    from tests.test_mpc_closed_loop import ENV, crossing_task

    task = crossing_task().replace(start=jnp.array([2.4, 3.5, np.pi]))  # 0.6 m from a table
    params = stack_params([task])
    state = EnvState(pose=params.start, t=jnp.zeros(1, jnp.int32))
    policy = jnp.array([[0.25, -0.5]])
    bridge = make_mpc_bridge(ENV, MPCConfig(unsafe_recovery=True))
    act, used, status = jax.jit(bridge)(
        jax.random.PRNGKey(0), jnp.array([True]), state, params, policy
    )
    assert int(status[0]) == SOLVED and bool(used[0])
    assert bridge.stats()["reasons"] == {"least_violation": 1}
    # the executed move does not bring the robot closer to the table than standing still
    _, nstate, _, _, _ = ENV.step(jax.random.PRNGKey(0), EnvState(params.start[0], 0), act[0], task)
    before = float(jnp.linalg.norm(params.start[0, :2] - jnp.array([3.0, 3.5])))
    after = float(jnp.linalg.norm(nstate.pose[:2] - jnp.array([3.0, 3.5])))
    assert after >= before - 1e-6


def _warm_start_config(**train_changes) -> ExperimentConfig:
    """One seed of the tiny config with MPC warm start, MPC buffer and cloning (no Q filter)."""
    from tests.test_training import TINY

    tc = dataclasses.replace(
        TINY.train,
        eps=0.2,
        tasks_per_iteration=2,
        initial_episodes=1,
        posterior_episodes=0,
        mpc_demo_share=1.0,
        mpc_demo_iterations=2,
        mpc_buffer_fraction=0.5,
        mpc_buffer_capacity=200,
        updates_per_iteration=200,  # meta-batches of 3 of 120 tasks: some hit tasks 0 and 1
        **train_changes,
    )
    pearl = TINY.pearl.replace(bc_weight=1.0, bc_q_filter=False)
    return TINY.replace(seeds=1, train=tc, pearl=pearl, mpc={"unsafe_recovery": True})


def test_warm_start_rows_fill_the_mpc_buffer_with_exactly_the_mpc_transitions():
    from mpcpearl_jax.trainer import Trainer

    tr = Trainer(_warm_start_config())
    state = tr.init_state()
    ids = jnp.array([[0, 1]])
    state, stats = tr.collect_phase(state, ids, 1, False, True, True, jnp.float32(1.0))
    assert float(stats["demo_rows"][0]) == 1.0
    assert float(stats["mpc_share"][0]) > 0.9  # the MPC drove (almost) every step
    n_mpc = int(round(float(stats["mpc_share"][0]) * 2 * tr.horizon))
    assert int(jnp.sum(state.mpc.size[0])) == n_mpc
    assert int(jnp.sum(state.rl.size[0])) == 2 * tr.horizon  # the RL buffer keeps everything
    # the stored MPC actions are what the episode applied: each is also in the RL buffer
    rl_actions = np.asarray(state.rl.data.action[0, 0, : tr.horizon])
    mpc_actions = np.asarray(state.mpc.data.action[0, 0, : int(state.mpc.size[0, 0])])
    for a in mpc_actions:
        assert np.min(np.abs(rl_actions - a).sum(-1)) < 1e-6
    # share 0: the paper's event-triggered infusion only
    state, stats = tr.collect_phase(state, ids, 1, False, True, True, jnp.float32(0.0))
    assert float(stats["demo_rows"][0]) == 0.0
    assert float(stats["mpc_share"][0]) <= float(stats["event_rate"][0]) + 1e-6
    state, losses = tr.update_phase(state)
    # only the MPC rows of tasks 0 and 1 are cloned: kept share > 0, finite error
    assert 0 < float(losses["bc_kept"][0]) < 1 and np.isfinite(float(losses["bc_error"][0]))


def test_pearl_baseline_never_builds_the_mpc_even_with_extensions_set():
    from mpcpearl_jax.trainer import Trainer
    from tests.test_training import TINY

    tc = dataclasses.replace(
        TINY.train, eps=0.0, mpc_demo_share=1.0, mpc_demo_iterations=5, mpc_buffer_fraction=0.5
    )
    tr = Trainer(TINY.replace(train=tc))
    assert tr.bridge is None and not tr.use_mpc_buffer and tr.init_state().mpc is None


def test_task_options_reach_the_builder_and_bad_ones_name_the_field():
    from mpcpearl_jax.trainer import Trainer
    from tests.test_training import TINY

    tr = Trainer(TINY.replace(task_options={"train_behaviours": 2}))
    assert tr.num_train == 16 and int(tr.test_tasks.start.shape[0]) == 24
    with pytest.raises(ConfigError, match="task_options"):
        Trainer(TINY.replace(task_options={"nosuch": 1}))
    with pytest.raises(ConfigError, match="task_options"):
        ExperimentConfig(task_options=[1])


def test_velocity_observation_matches_numpy():
    from mpcpearl_jax.envs import make_env, make_tasks

    base = make_env("restaurant")
    env = make_env("restaurant", observe_velocity=True)
    tasks = make_tasks("restaurant", "test", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[5], tasks)
    h = np.asarray(task.human_pos)  # [T + 1, H, 2]
    nh = h.shape[1]
    assert env.obs_dim(tasks) == base.obs_dim(tasks) + 2 * nh
    obs, state = env.reset(jax.random.PRNGKey(0), task)
    obs0, _ = base.reset(jax.random.PRNGKey(0), task)
    np.testing.assert_array_equal(obs[3 + 2 * nh : 3 + 4 * nh], 0.0)  # no motion before t = 0
    np.testing.assert_allclose(obs[: 3 + 2 * nh], obs0[: 3 + 2 * nh])
    np.testing.assert_allclose(obs[3 + 4 * nh :], obs0[3 + 2 * nh :])  # tables unchanged
    for t in range(1, 12):
        state = state.replace(t=jnp.asarray(t, jnp.int32))
        got = np.asarray(env.observe(state, task))[3 + 2 * nh : 3 + 4 * nh]
        want = np.clip((h[t] - h[t - 1]) / (4.0 * 0.05), -1, 1).reshape(-1)
        np.testing.assert_allclose(got, want, atol=1e-5)
    assert np.abs(got).max() > 0.5  # people walk at ~3.2 m/s early on


def test_redrawn_tasks_keep_the_layout_and_change_the_crowd_deterministically():
    from mpcpearl_jax.envs import make_env, make_tasks, redraw_tasks

    cfg = make_env("restaurant").config
    train = make_tasks("restaurant", "train", 0, config=cfg)
    ids = np.array([0, 17, 119])
    a = redraw_tasks("restaurant", 0, ids, (0, 5), config=cfg)
    b = redraw_tasks("restaurant", 0, ids, (0, 5), config=cfg)
    c = redraw_tasks("restaurant", 0, ids, (0, 6), config=cfg)
    orig = jax.tree_util.tree_map(lambda x: np.asarray(x)[ids], train)
    np.testing.assert_array_equal(np.asarray(a.static_lo), orig.static_lo)  # same tables
    np.testing.assert_array_equal(np.asarray(a.start), orig.start)
    np.testing.assert_array_equal(np.asarray(a.goal), orig.goal)
    np.testing.assert_array_equal(np.asarray(a.human_pos), np.asarray(b.human_pos))
    assert not np.allclose(np.asarray(a.human_pos), np.asarray(c.human_pos))
    assert not np.allclose(np.asarray(a.human_pos), orig.human_pos)
    # the redrawn crowd obeys the crowd model: nobody inside a table, people stand at the end
    pos, tables = np.asarray(a.human_pos), np.asarray(a.static_lo)
    d = np.linalg.norm(pos[:, :, :, None, :] - tables[:, None, None, :, :], axis=-1)
    assert d.min() > 0.5
    np.testing.assert_allclose(pos[:, -1], pos[:, -5], atol=1e-5)


def test_redraw_behaviours_changes_only_the_visited_tasks_and_needs_a_family_that_can():
    from mpcpearl_jax.trainer import Trainer
    from tests.test_training import TINY

    tc = dataclasses.replace(TINY.train, redraw_behaviours=True)
    tr = Trainer(TINY.replace(train=tc))
    state = tr.init_state()
    before = np.asarray(state.tasks.human_pos)
    state, ids = tr._choose_tasks(state, 2)
    state = tr._redraw(state, ids, 1)
    after = np.asarray(state.tasks.human_pos)
    ids = np.asarray(ids)
    for s in range(2):
        changed = np.flatnonzero(np.any(after[s] != before[s], axis=(1, 2, 3)))
        assert sorted(changed) == sorted(ids[s])
    again = tr._redraw(tr.init_state(), jnp.asarray(ids), 1)  # resume: same draw
    np.testing.assert_array_equal(np.asarray(again.tasks.human_pos), after)
    state, log = tr.iteration(tr.init_state())
    assert np.isfinite(log["train_return"])
    with pytest.raises(ConfigError, match="redraw_behaviours"):
        TrainConfig(redraw_behaviours="yes")
    sidewalk = pytest.importorskip("mpcpearl_jax.envs.sidewalk")
    del sidewalk
    from mpcpearl_jax.envs import can_redraw

    assert can_redraw("restaurant") and not can_redraw("sidewalk")


def _delays_of(orig: np.ndarray, got: np.ndarray, top: int) -> np.ndarray:
    """The per-person delay d with got[t] = orig[max(t - d, 0)] for one task [T + 1, H, 2]."""
    out = []
    for k in range(orig.shape[1]):
        fits = [
            d
            for d in range(top + 1)
            if np.array_equal(got[:, k], orig[np.maximum(np.arange(len(orig)) - d, 0), k])
        ]
        assert fits, f"person {k}: not its own path delayed by 0..{top} steps"
        out.append(fits[0])
    return np.asarray(out)


@pytest.mark.parametrize("redraw", [False, True])
def test_crowd_delays_shift_only_the_visited_paths_and_never_accumulate(redraw):
    from mpcpearl_jax.trainer import Trainer
    from tests.test_training import TINY

    top = 20
    tc = dataclasses.replace(TINY.train, crowd_delay_max=top, redraw_behaviours=redraw)
    tr = Trainer(TINY.replace(train=tc))
    state = tr.init_state()
    orig = np.asarray(tr.train_tasks.human_pos)
    seen = set()
    for visit in range(3):  # the same tasks visited again: delays drawn afresh from the paths
        ids = jnp.asarray([[0, 1], [1, 2]])
        before = np.asarray(state.tasks.human_pos)
        if redraw:
            state = tr._redraw(state, ids, visit + 1)
        fresh = np.asarray(state.tasks.human_pos)
        state = tr._delay_crowds(state, ids)
        after = np.asarray(state.tasks.human_pos)
        for s in range(2):
            changed = np.flatnonzero(np.any(after[s] != before[s], axis=(1, 2, 3)))
            assert set(changed) <= set(np.asarray(ids[s]).tolist())
            for i in np.asarray(ids[s]):
                base = fresh[s, i] if redraw else orig[i]
                seen.update(_delays_of(base, after[s, i], top).tolist())
    assert len(seen) > 5 and max(seen) <= top  # delays vary, within the bound
    # a resumed run (same state, same key) draws the same delays
    again = tr._delay_crowds(tr.init_state(), jnp.asarray([[0, 1], [1, 2]]))
    first = tr._delay_crowds(tr.init_state(), jnp.asarray([[0, 1], [1, 2]]))
    np.testing.assert_array_equal(np.asarray(again.tasks.human_pos), first.tasks.human_pos)
    state, log = tr.iteration(tr.init_state())
    assert np.isfinite(log["train_return"])
    state, log = tr.iteration(state)
    assert np.isfinite(log["train_return"])
    with pytest.raises(ConfigError, match="crowd_delay_max"):
        TrainConfig(crowd_delay_max=-1)
    with pytest.raises(ConfigError, match="crowd_delay_max"):
        TrainConfig(crowd_delay_max=2.5)


def _ego_ref(pose, points, scale):
    d = np.asarray(points, np.float64) - pose[:2]
    c, s = np.cos(pose[2]), np.sin(pose[2])
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
    return np.clip(local / scale, -1, 1)


@pytest.mark.parametrize("env_name", ["restaurant", "sidewalk"])
def test_relative_observation_matches_numpy(env_name):
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.envs.types import EnvState

    base = make_env(env_name)
    env = make_env(env_name, observe_relative=True)
    tasks = make_tasks(env_name, "test", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[1], tasks)
    nh, ns = task.human_pos.shape[1], task.static_lo.shape[0]
    n0 = base.obs_dim(tasks)
    assert env.obs_dim(tasks) == n0 + 2 * (nh + ns + 1)
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(env.config.arena_lo), np.asarray(env.config.arena_hi)
    for t in (0, 7, 30):
        pose = np.array([*rng.uniform(lo + 0.5, hi - 0.5), rng.uniform(-np.pi, np.pi)])
        state = EnvState(pose=jnp.asarray(pose, jnp.float32), t=jnp.asarray(t, jnp.int32))
        got = np.asarray(env.observe(state, task))
        np.testing.assert_allclose(got[:n0], np.asarray(base.observe(state, task)), atol=1e-6)
        h, m = np.asarray(task.human_pos[t]), np.asarray(task.human_mask[t])
        want_h = np.where(m[:, None], _ego_ref(pose, h, 5.0), 1.0).reshape(-1)
        nearest = np.clip(pose[:2], np.asarray(task.static_lo), np.asarray(task.static_hi))
        want_s = _ego_ref(pose, nearest, 5.0).reshape(-1)
        want_g = _ego_ref(pose, np.asarray(task.goal)[None], 5.0).reshape(-1)
        np.testing.assert_allclose(got[n0:], np.concatenate([want_h, want_s, want_g]), atol=1e-5)
    # a point straight ahead of the robot is at (+d, 0) in its frame
    pose = np.array([0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(_ego_ref(pose, [[0.0, 2.0]], 5.0), [[0.4, 0.0]], atol=1e-12)


def test_sensing_radius_hides_far_people_everywhere_in_the_observation():
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.envs.types import EnvState

    full = make_env("restaurant", observe_velocity=True, observe_relative=True)
    env = make_env("restaurant", observe_velocity=True, observe_relative=True, sensing_radius=3.0)
    tasks = make_tasks("restaurant", "test", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[3], tasks)
    nh, ns = task.human_pos.shape[1], task.static_lo.shape[0]
    assert env.obs_dim(tasks) == full.obs_dim(tasks)
    rng = np.random.default_rng(1)
    hidden_seen = 0
    for t in (1, 10, 25, 60):
        pose = np.array([*rng.uniform(-4.0, 4.0, 2), rng.uniform(-np.pi, np.pi)])
        state = EnvState(pose=jnp.asarray(pose, jnp.float32), t=jnp.asarray(t, jnp.int32))
        got, ref = np.asarray(env.observe(state, task)), np.asarray(full.observe(state, task))
        h, m = np.asarray(task.human_pos[t]), np.asarray(task.human_mask[t])
        m_prev = np.asarray(task.human_mask[t - 1])
        seen = m & (np.linalg.norm(h - pose[:2], axis=-1) <= 3.0)
        hidden_seen += int((m & ~seen).sum())
        want_h = np.where(seen[:, None], np.clip(h / 5.0, -1, 1), -1.0).reshape(-1)
        np.testing.assert_allclose(got[3 : 3 + 2 * nh], want_h, atol=1e-5)
        vel = got[3 + 2 * nh : 3 + 4 * nh].reshape(nh, 2)
        np.testing.assert_array_equal(vel[~(seen & m_prev)], 0.0)
        np.testing.assert_allclose(
            vel[seen & m_prev],
            ref[3 + 2 * nh : 3 + 4 * nh].reshape(nh, 2)[seen & m_prev],
            atol=1e-6,
        )
        off = 3 + 4 * nh + 2 * ns  # egocentric people
        ego = got[off : off + 2 * nh].reshape(nh, 2)
        np.testing.assert_array_equal(ego[~seen], 1.0)
        np.testing.assert_allclose(
            ego[seen], ref[off : off + 2 * nh].reshape(nh, 2)[seen], atol=1e-6
        )
        np.testing.assert_allclose(got[off + 2 * nh :], ref[off + 2 * nh :], atol=1e-6)  # static
        np.testing.assert_allclose(got[:3], ref[:3], atol=1e-6)
    assert hidden_seen > 0  # the case under test occurred
    with pytest.raises(ConfigError, match="sensing_radius"):
        make_env("restaurant", sensing_radius=-1.0)


def test_sorted_observation_lists_people_nearest_first_in_every_part():
    """`observe_sorted` permutes the people of every part of the observation (positions,
    velocities, egocentric positions) by their distance to the robot, people out of sensing range
    last; a NumPy reference builds the same vector from the unsorted observation."""
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.envs.types import EnvState

    opts = dict(observe_velocity=True, observe_relative=True, sensing_radius=3.0, observe_time=True)
    plain, env = make_env("restaurant", **opts), make_env("restaurant", observe_sorted=True, **opts)
    tasks = make_tasks("restaurant", "val", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[5], tasks)
    nh, ns = task.human_pos.shape[1], task.static_lo.shape[0]
    assert env.obs_dim(tasks) == plain.obs_dim(tasks)
    rng = np.random.default_rng(3)
    permuted = 0
    for t in (0, 3, 12, 20, 33, 50, 79):
        pose = np.array([*rng.uniform(-3.0, 3.0, 2), rng.uniform(-np.pi, np.pi)])
        state = EnvState(pose=jnp.asarray(pose, jnp.float32), t=jnp.asarray(t, jnp.int32))
        got, ref = np.asarray(env.observe(state, task)), np.asarray(plain.observe(state, task))
        h, m = np.asarray(task.human_pos[t], np.float64), np.asarray(task.human_mask[t])
        d = np.linalg.norm(h - pose[:2], axis=-1)
        seen = m & (d <= 3.0)
        order = np.argsort(np.where(seen, d, np.inf), kind="stable")
        permuted += int(np.any(order != np.arange(nh)))
        off_v, off_e = 3 + 2 * nh, 3 + 4 * nh + 2 * ns
        want = ref.copy()
        for lo in (3, off_v, off_e):  # the three per-person blocks
            want[lo : lo + 2 * nh] = ref[lo : lo + 2 * nh].reshape(nh, 2)[order].reshape(-1)
        np.testing.assert_allclose(got, want, atol=1e-6)
        ds = np.where(seen, d, np.inf)[order]
        k = int(seen.sum())
        assert np.all(np.isfinite(ds[:k])) and np.all(np.diff(ds[:k]) >= 0)  # nearest first
        assert np.all(np.isinf(ds[k:]))  # the unseen last
    assert permuted >= 3  # the reordering under test occurred
    with pytest.raises(ConfigError, match="observe_sorted"):
        make_env("restaurant", observe_sorted=1)


def test_observe_time_appends_the_elapsed_fraction_and_changes_nothing_else():
    from mpcpearl_jax.envs import make_env, make_tasks

    plain = make_env("restaurant", observe_velocity=True)
    env = make_env("restaurant", observe_velocity=True, observe_time=True)
    tasks = make_tasks("restaurant", "val", 0, config=env.config)
    task = jax.tree_util.tree_map(lambda x: x[2], tasks)
    assert env.obs_dim(tasks) == plain.obs_dim(tasks) + 1
    horizon = env.config.horizon
    actions = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (horizon, 2)), jnp.float32)
    key = jax.random.PRNGKey(0)
    (o, s), (p, q) = env.reset(key, task), plain.reset(key, task)
    for t in range(horizon):
        assert o.shape == (env.obs_dim(tasks),)
        np.testing.assert_allclose(o[-1], 2.0 * t / horizon - 1.0, atol=1e-6)
        np.testing.assert_array_equal(o[:-1], p)
        o, s, r, done, _ = env.step(key, s, actions[t], task)
        p, q, r_ref, _, _ = plain.step(key, q, actions[t], task)
        assert float(r) == float(r_ref)
    assert bool(done) and float(o[-1]) == 1.0


def test_grbal_refuses_env_options_its_model_or_planner_cannot_handle():
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.grbal.model import layout_of

    tasks = make_tasks("restaurant", "val", 0)
    for field, value in (
        ("observe_relative", True),
        ("sensing_radius", 2.0),
        ("observe_time", True),
        ("observe_sorted", True),
    ):
        with pytest.raises(ConfigError, match=f"env.{field}"):
            layout_of(make_env("restaurant", **{field: value}), tasks)


def _restaurant_task():
    from mpcpearl_jax.envs import make_env, make_tasks

    env = make_env("restaurant")
    tasks = make_tasks("restaurant", "train", 0, config=env.config)
    return env, jax.tree_util.tree_map(lambda x: x[0], tasks)


def test_random_start_is_free_in_the_arena_and_outside_the_goal():
    env, task = _restaurant_task()
    cfg = env.config
    poses = np.asarray(
        jax.vmap(lambda k: env.random_start(k, task))(jax.random.split(jax.random.PRNGKey(0), 400))
    )
    assert poses.shape == (400, 3) and np.all(np.isfinite(poses))
    assert np.all(np.abs(poses[:, 2]) <= np.pi)
    lo = np.asarray(cfg.arena_lo) + cfg.robot_radius
    hi = np.asarray(cfg.arena_hi) - cfg.robot_radius
    assert np.all(poses[:, :2] >= lo) and np.all(poses[:, :2] <= hi)
    # NumPy reference of the two exclusions: no table or person present at t = 0 within reach,
    # not inside the goal region
    hp, hm = np.asarray(task.human_pos[0]), np.asarray(task.human_mask[0])
    slo, shi = np.asarray(task.static_lo), np.asarray(task.static_hi)
    srad = np.asarray(task.static_radius)
    for p in poses[:, :2]:
        d_s = np.linalg.norm(np.maximum(np.maximum(slo - p, p - shi), 0.0), axis=-1) - srad
        assert np.all(d_s >= cfg.robot_radius)
        d_h = np.linalg.norm(hp - p, axis=-1)[hm]
        assert np.all(d_h >= cfg.robot_radius + cfg.human_radius)
        assert np.linalg.norm(p - np.asarray(task.goal)) > cfg.goal_radius
    # spread over the arena, not a handful of spots
    assert np.std(poses[:, 0]) > 2.0 and np.std(poses[:, 1]) > 2.0
    assert len(np.unique(np.round(poses[:, :2], 3), axis=0)) == 400


def test_random_start_falls_back_to_the_task_start_when_nothing_is_free():
    env, task = _restaurant_task()
    blocked = task.replace(  # one box over the whole arena: no candidate is free
        static_lo=task.static_lo.at[0].set(jnp.array([-5.0, -5.0])),
        static_hi=task.static_hi.at[0].set(jnp.array([5.0, 5.0])),
    )
    pose = env.random_start(jax.random.PRNGKey(3), blocked)
    np.testing.assert_array_equal(np.asarray(pose), np.asarray(task.start, np.float32))


def test_exploring_starts_change_only_the_marked_rows_and_never_the_encoder_context():
    from mpcpearl_jax.envs.types import EnvState
    from mpcpearl_jax.trainer import Trainer
    from tests.test_training import TINY

    tc = dataclasses.replace(TINY.train, explore_start_share=0.9)
    tr = Trainer(TINY.replace(train=tc))
    state = tr.init_state()
    # the collector: rows marked explore start at env.random_start, the others at the start
    ids = jnp.array([[0, 1, 0, 1]] * TINY.seeds)
    tasks = jax.vmap(lambda t, i: jax.tree_util.tree_map(lambda x: x[i], t))(state.tasks, ids)
    z = jnp.zeros((TINY.seeds, 4, TINY.pearl.latent_dim))
    explore = jnp.array([[True, False, True, False]] * TINY.seeds)
    key = jax.random.PRNGKey(5)
    ep = jax.jit(tr._collector)(key, state.learner.params["policy"], z, tasks, None, explore)
    start = np.asarray(tasks.start[..., :2])
    first = np.asarray(ep.position[:, :, 0])
    np.testing.assert_allclose(first[:, [1, 3]], start[:, [1, 3]], atol=1e-6)
    assert np.all(np.linalg.norm(first[:, [0, 2]] - start[:, [0, 2]], axis=-1) > 1e-3)
    # the first observation of an exploring row is the env's observation of its pose
    task = jax.tree_util.tree_map(lambda x: x[0, 0], tasks)
    obs0 = np.asarray(ep.transitions.obs[0, 0, 0])
    pose = jnp.array([first[0, 0, 0], first[0, 0, 1], obs0[2] * np.pi], jnp.float32)
    want = tr.env.observe(EnvState(pose=pose, t=jnp.zeros((), jnp.int32)), task)
    np.testing.assert_allclose(obs0, np.asarray(want), atol=1e-5)
    # the trainer: the prior phase (encoder context) never explores, the posterior phase does
    two = ids[:, :2]
    state, prior = tr.collect_phase(state, two, 1, False, True, True, jnp.float32(0.0))
    state, post = tr.collect_phase(state, two, 1, True, False, False, jnp.float32(0.0))
    assert float(jnp.sum(prior["explore_rows"])) == 0.0
    assert float(jnp.sum(post["explore_rows"])) > 0.0
    for s_ in range(TINY.seeds):
        for t_ in (0, 1):
            task = jax.tree_util.tree_map(lambda x, s_=s_, t_=t_: x[s_, t_], state.tasks)
            start_obs = np.asarray(tr.env.reset(key, task)[0])
            np.testing.assert_allclose(
                np.asarray(state.enc.data.obs[s_, t_, 0]), start_obs, atol=1e-5
            )
    state, log = tr.iteration(state)
    assert np.isfinite(log["train_return"]) and 0.0 < log["train_explore_rows"] <= 1.0


@pytest.mark.parametrize(
    "folder, option",
    [
        ("dagger-labels-60min", "train.mpc_dagger_labels"),
        ("policy-ema-60min", "pearl.policy_ema"),
        ("collision-penalty-60min", "env_overrides.w_collision"),
    ],
)
def test_runs_of_removed_options_evaluate_but_do_not_resume(tmp_path, folder, option):
    """docs/extensions.md, Removed options: a committed run that switched one on loads with the
    option dropped (its policy acts), resuming it is refused naming the option, and the option
    can no longer be set; a config.json with the option at its off value resumes as before."""
    import json

    from mpcpearl_jax import load_policy
    from mpcpearl_jax.checkpoint import load_config
    from mpcpearl_jax.config import REMOVED_OPTIONS, removed_options_on
    from mpcpearl_jax.errors import CheckpointError

    run = Path(__file__).resolve().parents[1] / "results" / "restaurant" / "ablation" / folder
    raw = json.loads((run / "config.json").read_text())
    assert removed_options_on(raw) == [option]
    cfg = load_config(run)
    section, field = option.split(".")
    part = getattr(cfg, section)
    assert field not in (part if isinstance(part, dict) else part.__dict__)
    policy = load_policy(run)
    act = policy.act(jnp.zeros((policy.obs_dim,)), policy.prior_z())
    assert act.shape == (2,) and bool(jnp.all(jnp.isfinite(act)))
    with pytest.raises(CheckpointError, match=option):
        load_config(run, resume=True)
    off = json.loads(json.dumps(raw))
    off[section][field] = REMOVED_OPTIONS[section][field]
    (tmp_path / "config.json").write_text(json.dumps(off))
    assert load_config(tmp_path, resume=True) == cfg
    from mpcpearl_jax.envs import make_env

    build = {"train": TrainConfig, "pearl": PearlConfig}.get(section)
    build = build or (lambda **kw: make_env("restaurant", **kw))
    with pytest.raises((TypeError, ValueError)):
        build(**{field: 1})
