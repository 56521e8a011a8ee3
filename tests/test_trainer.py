"""The trainer's optional collection paths (trainer.py, collect.py): re-drawn crowds, randomised
crowd timing, exploring starts, task options; each off in the paper's configuration
(docs/extensions.md)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.config import ExperimentConfig, TrainConfig
from mpcpearl_jax.errors import ConfigError


def test_pearl_baseline_never_builds_the_mpc():
    from mpcpearl_jax.training.trainer import Trainer
    from tests.test_training import TINY

    tr = Trainer(TINY.replace(train=dataclasses.replace(TINY.train, eps=0.0)))
    assert tr.bridge is None


def test_task_options_reach_the_builder_and_bad_ones_name_the_field():
    from mpcpearl_jax.training.trainer import Trainer
    from tests.test_training import TINY

    tr = Trainer(TINY.replace(task_options={"train_behaviours": 2}))
    assert tr.num_train == 16 and int(tr.test_tasks.start.shape[0]) == 24
    with pytest.raises(ConfigError, match="task_options"):
        Trainer(TINY.replace(task_options={"nosuch": 1}))
    with pytest.raises(ConfigError, match="task_options"):
        ExperimentConfig(task_options=[1])


@pytest.mark.slow  # (~21 s)
def test_redraw_behaviours_changes_only_the_visited_tasks_and_needs_a_family_that_can():
    from mpcpearl_jax.training.trainer import Trainer
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
    from mpcpearl_jax.training.trainer import Trainer
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


@pytest.mark.slow  # (~21 s)
def test_exploring_starts_change_only_the_marked_rows_and_never_the_encoder_context():
    from mpcpearl_jax.envs.types import EnvState
    from mpcpearl_jax.training.trainer import Trainer
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
    ep = jax.jit(tr._collector)(key, state.learner.params["policy"], z, tasks, explore)
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
    state, prior = tr.prior_collection(state, two)
    state, post = tr.posterior_collection(state, two)
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
