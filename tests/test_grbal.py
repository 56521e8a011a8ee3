"""GrBAL baseline: inner step and meta-gradient, planner, tracing, the CLI end to end."""

import json
from pathlib import Path

import chex
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.grbal.config import GrbalConfig, GrbalExperimentConfig
from mpcpearl_jax.grbal.model import (
    DynamicsModel,
    ObsLayout,
    fit_normalizer,
    make_meta_loss,
    make_meta_step,
    sample_windows,
    targets,
)
from mpcpearl_jax.grbal.planner import mppi
from mpcpearl_jax.pearl import buffers
from mpcpearl_jax.pearl.types import Transitions

ZARA = Path(__file__).resolve().parents[2] / "shared" / "data" / "crowds_zara01.txt"
TINY = ObsLayout(num_humans=1, num_velocity=0, num_static=1)  # obs [x, y, th, hx, hy, sx, sy]


def _windows(key, n, length, layout=TINY):
    k1, k2, k3 = jax.random.split(key, 3)
    o = jax.random.uniform(k1, (n, length, layout.obs_dim), minval=-0.9, maxval=0.9)
    a = jax.random.uniform(k2, (n, length, 2), minval=-1.0, maxval=1.0)
    no = o + 0.05 * jax.random.normal(k3, o.shape)
    no = no.at[..., layout.dyn_dim :].set(o[..., layout.dyn_dim :])  # static part constant
    return Transitions(o, a, jnp.zeros((n, length)), no, jnp.zeros((n, length)))


def test_config_errors_name_the_field():
    with pytest.raises(ConfigError, match="GrbalConfig.past"):
        GrbalConfig(past=0)
    with pytest.raises(ConfigError, match="GrbalConfig.robot_model"):
        GrbalConfig(robot_model="oracle")
    with pytest.raises(ConfigError, match="GrbalConfig.inner_lr"):
        GrbalConfig(inner_lr=-1.0)
    with pytest.raises(ConfigError, match="GrbalConfig.windows"):
        GrbalConfig(windows=8, meta_batch=24)
    with pytest.raises(ConfigError, match="GrbalExperimentConfig.seeds"):
        GrbalExperimentConfig(seeds=0)
    cfg = GrbalExperimentConfig(grbal=GrbalConfig(hidden=(8, 8)))
    assert GrbalExperimentConfig.from_dict(json.loads(cfg.to_json())) == cfg


def test_inner_step_meta_gradient_matches_finite_differences():
    """The outer gradient through one inner SGD step (second order), from the factored inner step
    of the meta-loss, equals central finite differences of the plain definition
    L_future(theta - alpha grad L_past(theta)) in float64; the values agree too."""
    with jax.enable_x64(True):
        model = DynamicsModel(TINY, (5, 4))
        to64 = lambda t: jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), t)  # noqa: E731
        params = to64(model.init(jax.random.PRNGKey(0)))
        w = to64(_windows(jax.random.PRNGKey(1), 3, 5))
        valid = jnp.ones(w.reward.shape, bool)
        norm = to64(jax.jit(fit_normalizer, static_argnums=2)(w, valid, TINY))
        past, lr = 2, 0.3  # a large step so that the second-order term matters

        def reference(p):
            def one(win):
                adapted = model.adapt(
                    p, norm, win.obs[:past], win.action[:past], win.next_obs[:past], lr
                )
                return model.loss(
                    adapted, norm, win.obs[past:], win.action[past:], win.next_obs[past:]
                )

            return jnp.mean(jax.vmap(one)(w))

        meta_loss = make_meta_loss(model, past, lr)
        reference = jax.jit(reference)
        value, _ = jax.jit(meta_loss)(params, norm, w)
        np.testing.assert_allclose(value, reference(params), rtol=1e-10)
        grad = jax.jit(jax.grad(lambda p: meta_loss(p, norm, w)[0]))(params)
        flat, unravel = jax.flatten_util.ravel_pytree(params)
        g_flat = jax.flatten_util.ravel_pytree(grad)[0]
        rng = np.random.default_rng(0)
        h = 1e-6
        for _ in range(4):  # random directions
            v = jnp.asarray(rng.normal(size=flat.shape))
            fd = (reference(unravel(flat + h * v)) - reference(unravel(flat - h * v))) / (2 * h)
            np.testing.assert_allclose(float(g_flat @ v), float(fd), rtol=1e-6, atol=1e-9)

        # the first-order approximation (no gradient through the inner step) is measurably off
        def first_order(p):
            def one(win):
                gp = jax.grad(model.loss)(
                    p, norm, win.obs[:past], win.action[:past], win.next_obs[:past]
                )
                adapted = jax.tree_util.tree_map(
                    lambda x, g: x - lr * jax.lax.stop_gradient(g), p, gp
                )
                return model.loss(
                    adapted, norm, win.obs[past:], win.action[past:], win.next_obs[past:]
                )

            return jnp.mean(jax.vmap(one)(w))

        fo = jax.flatten_util.ravel_pytree(jax.jit(jax.grad(first_order))(params))[0]
        assert float(jnp.linalg.norm(fo - g_flat)) > 1e-4 * float(jnp.linalg.norm(g_flat))


def test_targets_wrap_the_heading():
    o = jnp.zeros((TINY.obs_dim,)).at[2].set(0.99)
    no = o.at[2].set(-0.99)
    d = targets(o, no, TINY)
    assert d.shape == (TINY.dyn_dim,)
    np.testing.assert_allclose(d[2], 0.02, atol=1e-6)


def test_mppi_finds_the_optimum_of_a_quadratic():
    target = jax.random.uniform(jax.random.PRNGKey(3), (10, 2), minval=-0.8, maxval=0.8)
    cost = lambda u: jnp.sum((u - target[None]) ** 2, axis=(1, 2))  # noqa: E731
    solve = jax.jit(
        lambda k: mppi(
            cost,
            jnp.zeros((10, 2)),
            k,
            num_samples=256,
            iterations=60,
            noise_std=0.1,
            temperature=0.2,
        )
    )
    mean, best = solve(jax.random.PRNGKey(0))
    assert float(jnp.max(jnp.abs(mean - target))) < 0.05
    # the box is respected: an optimum outside it is met at the bound
    far = jnp.full((10, 2), 1.5)
    mean, _ = mppi(
        lambda u: jnp.sum((u - far[None]) ** 2, axis=(1, 2)),
        jnp.zeros((10, 2)),
        jax.random.PRNGKey(1),
        num_samples=128,
        iterations=30,
        noise_std=0.3,
        temperature=0.2,
    )
    assert float(jnp.max(mean)) <= 1.0 and float(jnp.min(mean)) > 0.8


def test_planner_cost_is_the_env_reward_on_predicted_states():
    """With the robot on eq. (1) (robot_model="known") and a model that predicts no change, the
    planner's cost of an action sequence is minus the env's eq. (2) rewards of the same actions
    in a task whose people stand still."""
    from mpcpearl_jax.envs import make_env, make_tasks
    from mpcpearl_jax.grbal.model import identity_normalizer, layout_of
    from mpcpearl_jax.grbal.planner import Planner

    env = make_env("restaurant")
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test"))
    people = task.human_pos[10].at[0].set(jnp.array([-4.8, 5.0]))  # 0.58 m behind the start
    task = task.replace(human_pos=jnp.broadcast_to(people, task.human_pos.shape))
    layout = layout_of(env, task)
    model = DynamicsModel(layout, (8,))
    zero = jax.tree_util.tree_map(jnp.zeros_like, model.init(jax.random.PRNGKey(0)))
    planner = Planner(
        model, env.config, horizon=12, num_samples=4, iterations=1, noise_std=0.1,
        temperature=1.0, gamma=1.0, robot_model="known",
    )  # fmt: skip
    u = jnp.stack([jnp.full(12, -0.6), jnp.linspace(-0.5, 0.5, 12)], axis=-1)
    obs0, st = env.reset(jax.random.PRNGKey(0), task)
    rewards = []
    for t in range(12):  # people standing still; the robot leaves person 0 behind
        _, st, r, _, info = env.step(jax.random.PRNGKey(0), st, u[t], task)
        assert not bool(info.collision)
        rewards.append(float(r))
    assert min(rewards) < -20  # the safety term of eq. (2) is part of the comparison
    cost = jax.jit(planner.sequence_cost)(zero, identity_normalizer(layout), obs0, u, task)
    np.testing.assert_allclose(float(cost), -sum(rewards), rtol=1e-4)


def test_meta_step_traces_once_and_learns():
    model = DynamicsModel(TINY, (16, 16))
    opt = optax.adam(1e-2)
    params = model.init(jax.random.PRNGKey(0))
    opt_state = opt.init(params)
    step = jax.jit(chex.assert_max_traces(make_meta_step(model, 4, 1e-2, opt), n=1))
    batches = [_windows(jax.random.PRNGKey(i), 24, 8) for i in range(2)]
    norm = fit_normalizer(batches[0], jnp.ones(batches[0].reward.shape, bool), TINY)
    losses = []
    for i in range(30):
        params, opt_state, m = step(params, opt_state, norm, batches[i % 2])
        losses.append(float(m.post_loss))
    assert np.all(np.isfinite(losses)) and losses[-1] < losses[0]
    chex.clear_trace_counter()


def test_windows_are_consecutive_steps_of_one_episode():
    horizon, eps, n_tasks = 10, 3, 4
    buf = buffers.init_buffer(n_tasks, eps * horizon, 3, 2)
    insert = jax.jit(buffers.insert)
    for e in range(eps + 1):  # one more than fits: the ring overwrites whole episodes
        t = np.broadcast_to(np.arange(horizon, dtype=np.float32), (n_tasks, horizon))
        obs = np.stack([t, np.full_like(t, e), np.zeros_like(t)], axis=-1)
        data = Transitions(obs, np.zeros((n_tasks, horizon, 2), np.float32), t, obs, 0 * t)
        buf = insert(buf, jnp.arange(n_tasks), data)
    sample = jax.jit(sample_windows, static_argnums=(2, 3, 4, 5, 6))
    w = sample(buf, jax.random.PRNGKey(0), n_tasks, 4, 64, 6, horizon)
    assert w.obs.shape == (64, 6, 3)
    steps, episode = np.asarray(w.obs[..., 0]), np.asarray(w.obs[..., 1])
    assert np.all(np.diff(steps, axis=1) == 1)
    assert np.all(episode == episode[:, :1])
    assert set(np.unique(episode)) <= {1.0, 2.0, 3.0}  # episode 0 was overwritten


def _run_cli(argv):
    from experiments import grbal

    assert grbal.main(argv) == 0


@pytest.fixture(scope="module")
def grbal_run(tmp_path_factory):
    """A smoke GrBAL run on the restaurant: stopped by its time budget after iteration 1, then
    resumed to iteration 2, from the command line."""
    out = tmp_path_factory.mktemp("grbal") / "g"
    base = ["--preset", "smoke", "--out", str(out), "--no-progress"]
    _run_cli([*base, "--iterations", "5", "--minutes", "1e-4"])  # stops after iteration 1
    _run_cli([*base, "--iterations", "2", "--resume"])
    return out


def test_grbal_cli_restaurant_resumes_and_reports(grbal_run):
    out = grbal_run
    log = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2]
    assert all(np.isfinite(r["model_post_loss"]) for r in log)
    assert {"test_SR", "test_online_SR", "test_adapt_SR"} <= set(log[-1])
    res = json.loads((out / "results.json").read_text())
    assert res["label"] == "GrBAL" and res["config"]["method"] == "grbal"
    for split in ("test_adapt", "test_online", "ood_adapt"):
        assert set(res[split]) >= {"SR", "TT", "CFR", "SPL", "MGD"}
    assert (out / "trajectory_test0.png").is_file() and (out / "learning_curves.png").is_file()
    assert (out / "policy.msgpack").is_file()


@pytest.mark.slow  # (~45 s; the run itself: test_grbal_cli_restaurant_resumes_and_reports)
def test_grbal_run_compares_and_evaluates_from_its_folder(grbal_run, tmp_path):
    import shutil

    out = tmp_path / "g"
    shutil.copytree(grbal_run, out)  # the policy file is damaged below
    res = json.loads((out / "results.json").read_text())
    from lab import compare

    assert compare.main([str(out), "--out", str(tmp_path / "cmp")]) == 0
    table = (tmp_path / "cmp" / "table.md").read_text()
    assert "GrBAL (2 adapt. eps.)" in table and "worst performance" in table

    # experiments.evaluate reproduces the run's own numbers from config.json + policy.msgpack,
    # and scores it on other task sets (pooled over task seeds)
    from mpcpearl_jax.cli import evaluate

    for online, key in ((False, "test_adapt"), (True, "test_online")):
        ev = tmp_path / f"ev{online}"
        argv = [str(out), "--figures", "none", "--out", str(ev)] + ["--online"] * online
        assert evaluate.main(argv) == 0
        rec = json.loads((ev / "results.json").read_text())
        assert rec["controller"] == "grbal" and rec["label"] == "GrBAL"
        for m in ("SR", "TT", "CFR", "SPL", "MGD"):
            assert rec["metrics"][m] == pytest.approx(res[key][m], abs=1e-6), (key, m)
    pooled = tmp_path / "pooled"
    argv = [
        str(out),
        "--split",
        "val",
        "--task-seeds",
        "1-2",
        "--tasks",
        "0-2",
        "--out",
        str(pooled),
    ]
    assert evaluate.main(argv) == 0
    rec = json.loads((pooled / "results.json").read_text())
    assert rec["num_tasks"] == 6 and set(rec["pooled"]) >= {"SR", "CFR", "MGD"}
    assert evaluate.main([str(out), "--set", "trust_v=1", "--out", str(tmp_path / "x")]) == 2
    (out / "policy.msgpack").write_bytes(b"garbage")
    assert evaluate.main([str(out), "--out", str(tmp_path / "y")]) == 2
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_grbal_cli_rejects_bad_settings(tmp_path, capsys):
    from experiments import grbal

    assert grbal.main(["--set", "grbal.past=0", "--out", str(tmp_path)]) == 2
    assert "GrbalConfig.past" in capsys.readouterr().err
    assert grbal.main(["--set", "grbal.nope=1", "--out", str(tmp_path)]) == 2
    assert "nope" in capsys.readouterr().err


@pytest.mark.slow
def test_grbal_cli_sidewalk(tmp_path):
    """Sidewalk (UCY Zara 01 when the data file is there, else the synthetic crowd)."""
    argv = ["--env", "sidewalk", "--preset", "smoke", "--iterations", "1"]
    argv += ["--out", str(tmp_path), "--no-progress"]
    if ZARA.is_file():
        argv += ["--data", str(ZARA)]
    _run_cli(argv)
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["env"] == "sidewalk" and res["config"]["online_eval"] is True
    assert "SR" in res["test_online"]


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
