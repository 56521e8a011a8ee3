"""Animated episodes (mpcpearl_jax.evaluation.animate)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.evaluation import animate


def _gif(path):
    with Image.open(path) as im:
        return im.n_frames, im.size


@pytest.fixture(scope="module")
def straight_episode():
    """Restaurant test task 0 with a constant action (it runs into people and tables)."""
    env = make_env("restaurant")
    task = jax.tree_util.tree_map(lambda x: x[0], make_tasks("restaurant", "test", 0))
    traj = env.rollout(jax.random.PRNGKey(0), task, lambda k, o: jnp.array([0.0, 0.1]))
    return env, task, jax.tree_util.tree_map(np.asarray, traj)


def test_frame_steps_cover_the_episode():
    np.testing.assert_array_equal(animate.frame_steps(80, 90), np.arange(81))
    s = animate.frame_steps(250, 90)  # the sidewalk: every third step and the last
    assert s[0] == 0 and s[-1] == 250 and len(s) <= 90 and np.all(np.diff(s) <= 3)


def test_headings_from_positions_keep_the_last_direction():
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    h = animate.headings_from_positions(pos, 0.3)
    np.testing.assert_allclose(h, [0.3, 0.0, 0.0, np.pi / 2])


def test_gif_has_one_frame_per_step_and_stays_small(tmp_path, straight_episode):
    env, task, traj = straight_episode
    assert traj["collision"].any()  # collisions are flashed
    acted = ["MPC" if 20 <= t < 30 else "policy" for t in range(env.config.horizon)]
    path = animate.animate_episode(
        tmp_path / "a" / "episode.gif",
        task,
        env.config,
        traj["position"],
        traj["collision"],
        None,
        acted,
        title="test",
    )
    frames, (w, h) = _gif(path)
    assert frames == env.config.horizon + 1
    assert 300 <= w <= 400 and 300 <= h <= 450
    assert path.stat().st_size < 400_000


def test_long_episodes_are_subsampled(tmp_path, straight_episode):
    env, task, traj = straight_episode
    path = animate.animate_episode(
        tmp_path / "e.gif", task, env.config, traj["position"], max_frames=20, dpi=40
    )
    assert _gif(path)[0] == len(animate.frame_steps(env.config.horizon, 20)) <= 21


def test_animate_result_takes_evaluator_arrays(tmp_path, straight_episode):
    env, task, traj = straight_episode
    tasks = jax.tree_util.tree_map(lambda x: np.stack([x, x]), task)
    result = {  # [S = 1, N = 2, ...]
        "position": np.stack([traj["position"]] * 2)[None],
        "collision": np.stack([traj["collision"]] * 2)[None],
        "heading": np.zeros((1, 2, env.config.horizon + 1)),
        "return": np.zeros((1, 2)),
    }
    path = animate.animate_result(
        tmp_path / "r.gif", result, tasks, env.config, task=1, max_frames=10, dpi=40
    )
    assert _gif(path)[0] == len(animate.frame_steps(env.config.horizon, 10))


def test_animate_episode_checks_shapes(tmp_path, straight_episode):
    env, task, traj = straight_episode
    with pytest.raises(ValueError, match="collisions"):
        animate.animate_episode(
            tmp_path / "x.gif", task, env.config, traj["position"], traj["collision"][:-1]
        )
    with pytest.raises(ValueError, match="one task"):
        tasks = jax.tree_util.tree_map(lambda x: x[None], task)
        animate.animate_episode(tmp_path / "x.gif", tasks, env.config, traj["position"])
