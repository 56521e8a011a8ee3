"""The learner extension of docs/extensions.md: the MPC as a guide policy (`train.guide_share`);
off in every preset, checked by the properties it promises."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.config import PRESETS, TrainConfig
from mpcpearl_jax.errors import ConfigError


def test_every_preset_leaves_the_learner_extensions_off():
    for name, cfg in PRESETS.items():
        assert cfg.train.guide_share == 0, name


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: TrainConfig(guide_share=0.5, eps=0.0), "guide_share"),
        (lambda: TrainConfig(guide_share=1.0), "guide_share"),
        (lambda: TrainConfig(guide_share=-0.1), "guide_share"),
        (lambda: TrainConfig(guide_share=0.5, posterior_episodes=0), "guide_share"),
        (lambda: TrainConfig(guide_steps=0), "guide_steps"),
        (lambda: TrainConfig(guide_decrement=-1), "guide_decrement"),
        (lambda: TrainConfig(guide_success=1.5), "guide_success"),
        (lambda: TrainConfig(guide_window=-1), "guide_window"),
        (lambda: TrainConfig(guide_window=32), "guide_window"),  # without a guide
    ],
)
def test_bad_extension_settings_name_their_field(make, field):
    with pytest.raises(ConfigError, match=field):
        make()


# ---------------------------------------------------------------------------- the MPC as guide
@pytest.mark.slow  # (~20 s)
def test_the_guide_acts_on_every_step_before_the_hand_over_and_never_after():
    """A stand-in MPC marks its steps: with events switched off (eps so small no draw fires),
    exactly the steps t < handover of each row are the MPC's."""
    from mpcpearl_jax.collection import make_collector, rows_of
    from mpcpearl_jax.envs import make_env, tasks_for
    from mpcpearl_jax.pearl.networks import Networks
    from tests.test_training import TINY

    env = make_env("restaurant")
    tasks = tasks_for(TINY, "train", config=env.config)
    nets = Networks(TINY.pearl, env.obs_dim(tasks), env.action_dim)

    def bridge(key, fire, state, flat, a_pi, stamp):
        return jnp.full_like(a_pi, 0.25), fire, None

    collect = make_collector(env, nets, bridge, eps=1e-12)
    params = jax.vmap(nets.init)(jax.random.split(jax.random.PRNGKey(0), 1))["policy"]
    rows = rows_of(tasks, jnp.array([[0, 1, 2, 3]]))
    z = jnp.zeros((1, 4, TINY.pearl.latent_dim))
    handover = jnp.array([[0, 5, 17, env.config.horizon]], jnp.int32)
    ep = collect(jax.random.PRNGKey(1), params, z, rows, None, handover)
    t = np.arange(env.config.horizon)
    for r, h in enumerate(np.asarray(handover[0])):
        np.testing.assert_array_equal(np.asarray(ep.used_mpc[0, r]), t < h)
        acted = np.all(np.asarray(ep.transitions.action[0, r]) == 0.25, -1)
        np.testing.assert_array_equal(acted[:h], True)


def _guided_trainer(**changes):
    from mpcpearl_jax.training.trainer import Trainer
    from tests.test_training import TINY

    base = dict(eps=0.2, guide_share=0.5, guide_steps=30, guide_decrement=8)
    tc = dataclasses.replace(TINY.train, **{**base, **changes})
    return Trainer(TINY.replace(train=tc, mpc={"unsafe_recovery": True, "n_workers": 1}))


def test_the_roll_in_bound_shrinks_only_after_guided_success():
    tr = _guided_trainer(guide_success=0.5)
    state = tr.init_state()
    assert np.asarray(state.guide_h).tolist() == [30, 30]
    post = {"guide_rows": jnp.array([0.5, 0.0]), "guide_success": jnp.array([0.5, 1.0])}
    state = tr._shrink_roll_in(state, post)  # seed 1 had no guided row: keeps its bound
    assert np.asarray(state.guide_h).tolist() == [22, 30]
    post = {"guide_rows": jnp.array([0.5, 0.5]), "guide_success": jnp.array([0.25, 0.5])}
    for _ in range(5):
        state = tr._shrink_roll_in(state, post)
    assert np.asarray(state.guide_h).tolist() == [22, 0]  # never below 0
    tr.close()


def test_the_evidence_window_shrinks_the_bound_only_on_a_full_window_at_the_threshold():
    """guide_window = 6: rows pool over iterations; h moves only once >= 6 rows ended, by the
    pooled rate, and the window empties after each decision (a tumbling window)."""
    from types import SimpleNamespace

    from mpcpearl_jax.training.trainer import Trainer, TrainState
    from tests.test_training import TINY

    tc = dataclasses.replace(TINY.train, eps=0.2, guide_share=0.5, guide_window=6)
    trainer = SimpleNamespace(cfg=TINY.replace(train=tc))  # the rule reads only the config
    zero = jnp.zeros((2,), jnp.float32)
    state = TrainState(None, None, None, None, None, None, jnp.array([30, 30]), zero, zero)

    def it(state, count, hits):
        post = {
            "guide_rows": jnp.array(count, jnp.float32) / 8,
            "guide_success": jnp.array(hits, jnp.float32) / jnp.maximum(jnp.array(count), 1),
            "guide_count": jnp.array(count, jnp.float32),
            "guide_hits": jnp.array(hits, jnp.float32),
        }
        return Trainer._shrink_roll_in(trainer, state, post)  # type: ignore[arg-type]

    # seed 0: two iterations of 2/2 successes; the per-iteration rule would have shrunk twice
    state = it(state, [2, 2], [2, 0])
    state = it(state, [2, 2], [2, 0])
    assert np.asarray(state.guide_h).tolist() == [30, 30]
    assert np.asarray(state.guide_n).tolist() == [4.0, 4.0]
    # the window fills (6 rows): seed 0 at 4/6 >= 0.5 shrinks, seed 1 at 2/6 does not
    state = it(state, [2, 2], [0, 2])
    assert np.asarray(state.guide_h).tolist() == [22, 30]
    assert np.asarray(state.guide_n).tolist() == [0.0, 0.0]
    assert np.asarray(state.guide_hits).tolist() == [0.0, 0.0]
    # a new window starts empty: seed 1's earlier failures no longer count
    for _ in range(3):
        state = it(state, [2, 2], [1, 2])
    assert np.asarray(state.guide_h).tolist() == [14, 22]  # 3/6 is at the threshold


@pytest.mark.slow  # (~41 s)
def test_guided_rows_are_drawn_from_the_policy_rows_and_kept_out_of_its_success_rate():
    # no event draw fires (eps tiny): the MPC solves only the few guided steps
    tr = _guided_trainer(explore_start_share=0.5, guide_steps=4, eps=1e-9)
    state = tr.init_state()
    ids = jnp.array([[0, 1], [2, 3]])
    state, _ = tr.prior_collection(state, ids)  # the context of the posterior phase
    state, stats = tr.posterior_collection(state, ids)
    assert set(stats) >= {"guide_rows", "guide_success", "explore_rows", "success"}
    assert np.all(np.asarray(stats["guide_rows"]) + np.asarray(stats["explore_rows"]) <= 1.0)
    tr.close()


def test_a_checkpoint_holds_the_extension_state_and_restores_it_exactly(tmp_path):
    from mpcpearl_jax.training.checkpoint import Checkpointer
    from mpcpearl_jax.training.run import policy_params

    tr = _guided_trainer(guide_window=32)
    state = tr.init_state()
    assert np.asarray(state.guide_n).tolist() == [0.0, 0.0]  # an empty evidence window
    state, _ = tr.update_phase(state)  # parameters that differ from a fresh state's
    state = state.replace(
        guide_h=jnp.array([22, 14], jnp.int32),
        guide_n=jnp.array([5.0, 3.0]),
        guide_hits=jnp.array([2.0, 1.0]),
        iteration=state.iteration + 1,
    )
    ck = Checkpointer(tmp_path, keep=2)
    ck.save(1, state, policy_params(state))
    back = ck.restore(template=tr.init_state())
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.asarray(back.guide_h).tolist() == [22, 14]
    assert np.asarray(back.guide_n).tolist() == [5.0, 3.0]
    ck.close()
    tr.close()
