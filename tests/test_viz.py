"""The trajectory figure helper writes a real PNG for tables, boxes and several robots."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax.envs import drawing, make_env, make_tasks


def _episode(env, params, policy_seed):
    def policy(key, obs):
        del obs
        return jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0)

    traj = jax.jit(lambda k: env.rollout(k, params, policy))(jax.random.PRNGKey(policy_seed))
    return np.asarray(traj["position"]), np.asarray(traj["collision"])


def _png_ok(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > 20_000  # a drawn figure, not an empty canvas


def test_restaurant_figure(tmp_path):
    env = make_env("restaurant")
    params = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test"))
    pos_a, col_a = _episode(env, params, 0)
    # a path that drives through a table, so that collisions get starred
    centre = np.asarray(params.static_lo[2])
    pos_b = np.linspace(np.asarray(params.start[:2]), centre, env.config.horizon + 1)
    col_b = np.linalg.norm(pos_b[1:] - centre, axis=-1) < 0.75
    assert col_b.any()
    out = drawing.save_trajectory_figure(
        tmp_path / "figs" / "restaurant.png",
        params,
        {"random policy": pos_a, "straight line": pos_b},
        {"random policy": col_a, "straight line": col_b},
        env.config,
        title="restaurant test task 0",
    )
    assert out.exists()
    _png_ok(out)


def test_boxes_and_absent_people(tmp_path):
    """Sidewalk-like geometry: plain and rounded boxes, people present only part of the time."""
    params = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test"))
    mask = np.array(params.human_mask)
    mask[:40, 0] = False
    params = params.replace(
        static_lo=params.static_lo.at[0].set(jnp.array([-6.0, -6.0])),
        static_hi=params.static_hi.at[0].set(jnp.array([6.0, -4.5])),
        static_radius=params.static_radius.at[0].set(0.0).at[1].set(0.2),
        human_mask=jnp.asarray(mask),
    )
    params = params.replace(static_hi=params.static_hi.at[1].add(jnp.array([1.0, 0.5])))
    path = np.zeros((81, 2))
    out = drawing.save_trajectory_figure(tmp_path / "boxes.png", params, {"still": path})
    _png_ok(out)


def test_bad_inputs():
    tasks = make_tasks("restaurant", "test")
    with pytest.raises(ValueError, match="one task"):
        drawing.plot_episode(tasks, {"a": np.zeros((81, 2))})
    params = jax.tree_util.tree_map(lambda x: x[0], tasks)
    with pytest.raises(ValueError, match="collisions for 'a'"):
        drawing.plot_episode(params, {"a": np.zeros((81, 2))}, {"a": np.zeros(5, bool)})
