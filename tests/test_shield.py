"""The test-time safety shield (`mpcpearl_jax.mpc.shield`): NumPy reference of the clearance and of
the choice, invariants, the evaluator path, the goal-seeking control behind it, and the command
line."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.envs.numpy_ref import (
    bicycle,
    normalized_to_physical,
    rounded_box_clearance,
    task_to_numpy,
)
from mpcpearl_jax.mpc.shield import ShieldConfig, clearance, filter_action, shield_step


def _clearance_ref(pose, action, people, prev, seen, task, goal, cfg, lookahead):
    """NumPy loop: the smallest clearance over `lookahead` held steps (see shield.clearance)."""
    x, y, th = (float(v) for v in pose)
    vel = np.where(seen[:, None], people - prev, 0.0)
    lo = np.asarray(cfg.arena_lo) + cfg.robot_radius
    hi = np.asarray(cfg.arena_hi) - cfg.robot_radius
    worst = math.inf
    for k in range(1, lookahead + 1):
        v, delta = normalized_to_physical(action, cfg.v_max)
        if math.hypot(x - goal[0], y - goal[1]) <= cfg.robot_radius:
            v = 0.0
        x, y, th = bicycle(x, y, th, v, delta, cfg.dt, cfg.wheelbase)
        x, y = float(np.clip(x, lo[0], hi[0])), float(np.clip(y, lo[1], hi[1]))
        for j in range(people.shape[0]):
            if seen[j]:
                q = people[j] + k * vel[j]
                d = math.hypot(x - q[0], y - q[1]) - cfg.robot_radius - cfg.human_radius
                worst = min(worst, d)
        cs = rounded_box_clearance(
            np.array([x, y]), task["static_lo"], task["static_hi"], task["static_radius"]
        )
        worst = min(worst, float(np.min(cs)) - cfg.robot_radius)
    return worst


def _random_case(rng, tasks, n_tasks):
    i = int(rng.integers(n_tasks))
    task = jax.tree_util.tree_map(lambda x: x[i], tasks)
    pose = np.array([*rng.uniform(-4.5, 4.5, 2), rng.uniform(-np.pi, np.pi)], np.float32)
    people = np.array(task.human_pos[int(rng.integers(1, 60))], np.float32)
    # put a person next to the robot half the time so that the shield has work to do
    if rng.random() < 0.5:
        people[0] = pose[:2] + rng.normal(0, 0.5, 2)
    prev = people - rng.normal(0, 0.15, people.shape).astype(np.float32)
    seen = rng.random(people.shape[0]) < 0.8
    action = rng.uniform(-1, 1, 2).astype(np.float32)
    return i, task, pose, people, prev, seen, action


@pytest.mark.parametrize("lookahead", [1, 3])
def test_clearance_and_choice_match_numpy(lookahead):
    env = make_env("restaurant")
    cfg = env.config
    tasks = make_tasks("restaurant", "val", 1, config=cfg)
    shield = ShieldConfig(margin=0.05, lookahead=lookahead)
    rng = np.random.default_rng(lookahead)
    clear_fn = jax.jit(
        lambda pose, acts, ppl, prev, seen, task: clearance(
            pose, acts, ppl, prev, seen, task, task.goal, cfg, lookahead
        )
    )
    filt = jax.jit(
        lambda a, pose, ppl, prev, seen, task: filter_action(
            a, pose, ppl, prev, seen, task, cfg, shield
        )
    )
    intervened = 0
    for _ in range(40):
        i, task, pose, people, prev, seen, action = _random_case(rng, tasks, 24)
        tnp = task_to_numpy(tasks, i)
        cands = np.asarray(shield.candidates(jnp.asarray(action)))
        got = np.asarray(clear_fn(pose, cands, people, prev, seen, task))
        ref = np.array(
            [
                _clearance_ref(pose, c, people, prev, seen, tnp, tnp["goal"], cfg, lookahead)
                for c in cands
            ]
        )
        np.testing.assert_allclose(got, ref, atol=2e-4)
        # the choice, from the reference clearances
        a, did = filt(action, pose, people, prev, seen, task)
        safe = ref >= shield.margin
        if safe[0]:
            want = 0
        elif safe.any():
            want = int(np.argmin(np.where(safe, np.sum((cands - action) ** 2, -1), np.inf)))
        else:
            want = int(np.argmax(ref))
        np.testing.assert_allclose(np.asarray(a), cands[want], atol=1e-6)
        assert bool(did) == (want != 0)
        intervened += int(did)
    assert 5 <= intervened <= 35  # both branches are exercised


def test_safe_actions_pass_unchanged_and_the_candidates_start_with_the_action():
    shield = ShieldConfig()
    a = jnp.array([0.3, -0.2])
    cands = shield.candidates(a)
    assert cands.shape == (1 + len(shield.speeds) * (1 + len(shield.steers)), 2)
    np.testing.assert_array_equal(np.asarray(cands[0]), np.asarray(a))
    env = make_env("restaurant")
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test", 0))
    # nobody seen and the robot at its start, moving slowly into the free corner region
    pose = task.start
    people = jnp.zeros((6, 2))
    out, did = filter_action(
        jnp.array([-0.9, 0.0]), pose, people, people, jnp.zeros(6, bool), task, env.config, shield
    )
    assert not bool(did)
    np.testing.assert_allclose(np.asarray(out), [-0.9, 0.0])


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(margin=-0.1), "margin"),
        (dict(margin=2.0), "margin"),
        (dict(lookahead=0), "lookahead"),
        (dict(lookahead=1.5), "lookahead"),
        (dict(margin=True), "margin"),
        (dict(lookahead=True), "lookahead"),
        (dict(speeds=()), "speeds"),
        (dict(steers=(0.0, 1.5)), "steers"),
    ],
)
def test_bad_shield_settings_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=f"shield.{field}"):
        ShieldConfig(**kwargs)


def test_goal_seeking_control_collides_alone_and_not_behind_the_shield():
    """End to end through the environment: the straight-at-the-goal control of
    lab.diagnostics.shield hits a table on every one of these tasks; behind the shield the
    same
    control reaches the goal without a contact, and the shield acts on a minority of steps."""
    from lab.diagnostics.shield import goal_seeking_evaluator

    env = make_env("restaurant", sensing_radius=3.0)
    tasks = jax.tree_util.tree_map(lambda x: x[:6], make_tasks("restaurant", "val", 1))
    bare = jax.device_get(goal_seeking_evaluator(env, None)(tasks))
    shielded = jax.device_get(goal_seeking_evaluator(env, ShieldConfig(0.05, 2))(tasks))
    assert np.all(np.asarray(bare["collision"]).any(-1))
    assert not np.asarray(bare["shielded"]).any()
    assert not np.asarray(shielded["collision"]).any()
    assert np.all(np.asarray(shielded["in_goal"]).any(-1))
    rate = float(np.mean(shielded["shielded"]))
    assert 0.0 < rate < 0.5


@pytest.mark.slow  # (~14 s)
def test_evaluator_with_shield_reports_the_replaced_steps_and_changes_nothing_without():
    from mpcpearl_jax.config import PearlConfig
    from mpcpearl_jax.evaluation import evaluate as eval_lib
    from mpcpearl_jax.pearl.networks import Networks

    env = make_env("restaurant", sensing_radius=3.0)
    tasks = jax.tree_util.tree_map(lambda x: x[:3], make_tasks("restaurant", "test", 0))
    pcfg = PearlConfig(hidden=(16,), encoder_hidden=(16,), latent_dim=2)
    nets = Networks(pcfg, env.obs_dim(tasks), 2)
    params = jax.tree_util.tree_map(lambda x: x[None], nets.init(jax.random.PRNGKey(3)))
    key = jax.random.PRNGKey(0)
    plain = eval_lib.make_evaluator(env, nets, 1)(key, params, tasks)
    shielded = eval_lib.make_evaluator(env, nets, 1, shield=ShieldConfig())(key, params, tasks)
    assert not np.asarray(plain["shielded"]).any()
    n_sh = int(np.asarray(shielded["shielded"]).sum())
    n_col = int(np.asarray(plain["collision"]).sum())
    assert n_col > 0  # an untrained policy bumps into things ...
    assert n_sh > 0 and int(np.asarray(shielded["collision"]).sum()) < n_col  # ... less shielded


def test_shield_step_sees_only_what_the_observation_holds():
    """People beyond the sensing radius are invisible to the shield, as to the policy."""
    env_far = make_env("restaurant", sensing_radius=0.3)
    env_all = make_env("restaurant")
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test", 0))
    t = 10
    person = task.human_pos[t, 0]
    pose = jnp.array([person[0] - 0.6, person[1], 0.0])  # 0.6 m behind person 0, facing it
    state = env_all.reset(jax.random.PRNGKey(0), task)[1].replace(pose=pose, t=jnp.int32(t))
    fast = jnp.array([1.0, 0.0])  # full speed straight at the person
    _, did_all = shield_step(env_all, state, fast, task, ShieldConfig())
    _, did_far = shield_step(env_far, state, fast, task, ShieldConfig())
    assert bool(did_all) and not bool(did_far)


@pytest.mark.slow  # the command line of --shield (~11 s); the evaluator: fast
def test_evaluate_cli_shield(tmp_path, capsys):
    """`experiments.evaluate RUN --shield` on the committed headline policy (3 tasks): the record
    holds the shield settings and the replaced share; bad combinations are one-line errors."""
    from pathlib import Path

    from mpcpearl_jax.cli import evaluate

    run = Path(__file__).resolve().parents[1] / "results" / "restaurant" / "mpc-pearl-eps0.2"
    out = tmp_path / "ev"
    rc = evaluate.main(
        [
            str(run),
            "--split",
            "val",
            "--tasks",
            "0-2",
            "--figures",
            "none",
            "--shield",
            "--shield-lookahead",
            "2",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    rec = json.loads((out / "results.json").read_text())
    assert rec["shield"]["lookahead"] == 2 and rec["shield"]["margin"] == 0.05
    assert 0.0 <= rec["shield_rate"] <= 1.0
    assert "shield" in rec["label"]
    for argv, msg in [
        ([str(run), "--shield-margin", "0.1"], "need --shield"),
        ([str(run), "--shield-margin", "0.05"], "need --shield"),
        ([str(run), "--shield", "--shield-margin", "5"], "--shield-margin"),
        (["--controller", "gp-mpc", "--shield"], "applies to --controller policy"),
    ]:
        capsys.readouterr()
        assert evaluate.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1
