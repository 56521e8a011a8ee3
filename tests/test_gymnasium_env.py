"""The Gymnasium env and vector env (mpcpearl_jax.envs.gymnasium_adapter): Gymnasium's checker,
steps equal to the JAX env's, task draws, autoreset, frames, registration and the example."""

from __future__ import annotations

import importlib
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

# gymnasium is an optional extra (`gymnasium`; the `dev` extra includes it)
gym = pytest.importorskip(
    "gymnasium", reason='gymnasium not installed (an optional extra): pip install -e ".[gymnasium]"'
)

from gymnasium.utils.env_checker import check_env  # noqa: E402
from gymnasium.vector import AutoresetMode  # noqa: E402

from mpcpearl_jax.envs import gymnasium_adapter as ga  # noqa: E402
from mpcpearl_jax.envs import make_env, make_tasks  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESTAURANT, SIDEWALK = ga.ENV_IDS["restaurant"], ga.ENV_IDS["sidewalk"]


def _take(params, i):
    return jax.tree_util.tree_map(lambda x: x[i], params)


def _actions(n, seed=0, shape=(2,)):
    """Random actions, some beyond the box (the env clips them, like the JAX env)."""
    return np.random.default_rng(seed).uniform(-1.2, 1.2, (n, *shape)).astype(np.float32)


@pytest.mark.parametrize("env_id", [RESTAURANT, SIDEWALK])
def test_check_env_passes_without_a_warning(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)  # renders too: the spec makes it again with each render mode
    assert not [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert isinstance(env.unwrapped, ga.GymNavEnv)
    space = env.observation_space
    assert space.dtype == np.float32 and np.all(space.low == -1) and np.all(space.high == 1)
    assert env.action_space.shape == (2,) and np.all(env.action_space.high == 1)
    env.close()


@pytest.mark.parametrize("family,steps", [("restaurant", None), ("sidewalk", 40)])
def test_steps_match_the_jax_env(family, steps):
    """The same task and actions give the JAX env's observations, rewards, events and end."""
    env = ga.GymNavEnv(family, split="test")
    nav = make_env(family)
    tasks = make_tasks(family, "test", 0)
    params = _take(tasks, 2)
    steps = steps or nav.config.horizon
    obs, info = env.reset(seed=5, options={"task": 2})
    assert info == {"task": 2, "t": 0} and env.task == 2
    j_obs, state = nav.reset(jax.random.PRNGKey(0), params)
    np.testing.assert_allclose(obs, j_obs, atol=1e-6)
    j_step = jax.jit(nav.step)
    for t, a in enumerate(_actions(steps)):
        obs, reward, terminated, truncated, info = env.step(a)
        j_obs, state, j_r, j_done, j_info = j_step(jax.random.PRNGKey(t), state, a, params)
        np.testing.assert_allclose(obs, j_obs, atol=1e-6)
        np.testing.assert_allclose(reward, float(j_r), rtol=1e-6, atol=1e-5)
        assert terminated is False and truncated is bool(j_done)  # the horizon truncates
        for m in ga.METRIC_NAMES:
            assert info[m] == type(info[m])(getattr(j_info, m)), (t, m)
        assert info["t"] == t + 1 and obs in env.observation_space
    assert truncated == (steps == nav.config.horizon)


def test_reset_draws_the_task_from_the_seed_or_takes_the_fixed_one():
    env = ga.GymNavEnv("restaurant", split="train")
    assert env.num_tasks == 120
    drawn = [env.reset(seed=s)[1]["task"] for s in range(12)]
    assert drawn == [env.reset(seed=s)[1]["task"] for s in range(12)]
    assert len(set(drawn)) > 6
    assert env.reset(seed=0, options={"task": 7})[1]["task"] == 7
    fixed = ga.GymNavEnv("restaurant", split="train", task=11)
    assert {fixed.reset(seed=s)[1]["task"] for s in range(4)} == {11}
    assert fixed.reset(options={"task": 3})[1]["task"] == 3  # the option wins
    for bad in (120, -1, 1.5):
        with pytest.raises(ValueError, match="task must be an index"):
            env.reset(options={"task": bad})
    with pytest.raises(ValueError, match="action must have shape"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(gym.error.ResetNeeded):
        ga.GymNavEnv("restaurant", split="test").step(np.zeros(2, np.float32))


def test_own_tasks_and_env_overrides():
    """`tasks=` (one task or stacked) instead of a split; `env_overrides` reach the NavConfig
    and the observation space follows them."""
    one = _take(make_tasks("restaurant", "test", 0), 4)
    env = ga.GymNavEnv("restaurant", tasks=one, env_overrides={"observe_time": True})
    assert env.num_tasks == 1 and env.nav.config.observe_time
    obs, info = env.reset(seed=0)
    assert info["task"] == 0 and obs.shape == (26,) and obs[-1] == -1.0  # the time entry
    np.testing.assert_allclose(env.task_params().goal, one.goal)


def test_render_gives_the_frames_of_the_episode():
    env = gym.make(RESTAURANT, render_mode="rgb_array", split="test")
    env.reset(seed=0)
    first = env.render()
    for a in _actions(5):
        env.step(a)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.shape == first.shape and not np.array_equal(frame, first)
    assert 0 < frame.mean() < 255
    quiet = ga.GymNavEnv("restaurant", split="test")
    quiet.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert quiet.render() is None


def _vector_jax(nav, tasks, task, actions, horizon):
    """The vmapped JAX env on fixed tasks: per-step obs, reward, done over `actions` [K, N, 2],
    resetting each slot after its horizon as Gymnasium's next-step autoreset does."""
    params = _take(tasks, jnp.asarray(task))
    v_reset = jax.jit(jax.vmap(nav.reset, in_axes=(None, 0)))
    v_step = jax.jit(jax.vmap(nav.step, in_axes=(None, 0, 0, 0)))
    obs, state = v_reset(jax.random.PRNGKey(0), params)
    first, out, ended = obs, [], False
    for a in actions:
        if ended:
            obs, state = v_reset(jax.random.PRNGKey(0), params)
            out.append((obs, np.zeros(len(task)), np.zeros(len(task), bool)))
            ended = False
            continue
        obs, state, r, done, _ = v_step(jax.random.PRNGKey(0), state, jnp.asarray(a), params)
        out.append((obs, r, done))
        ended = bool(np.asarray(done).any())
    return first, out


def test_vector_env_matches_the_vmapped_jax_env_with_next_step_autoreset():
    n, task = 4, [0, 5, 5, 23]
    envs = ga.GymNavVectorEnv(n, "restaurant", split="test", task=task)
    nav, tasks = make_env("restaurant"), make_tasks("restaurant", "test", 0)
    horizon = nav.config.horizon
    actions = _actions(horizon + 3, seed=1, shape=(n, 2))
    obs, info = envs.reset(seed=0)
    first, want = _vector_jax(nav, tasks, task, actions, horizon)
    np.testing.assert_allclose(obs, first, atol=1e-6)
    np.testing.assert_array_equal(info["task"], task)
    for k, a in enumerate(actions):
        obs, reward, terminated, truncated, info = envs.step(a)
        w_obs, w_r, w_done = want[k]
        np.testing.assert_allclose(obs, w_obs, atol=1e-6)
        np.testing.assert_allclose(reward, w_r, rtol=1e-6, atol=1e-5)
        np.testing.assert_array_equal(truncated, w_done)
        assert not terminated.any() and obs in envs.observation_space
        np.testing.assert_array_equal(info["task"], task)  # fixed tasks survive the autoreset
    # the step after the horizon reset every slot: reward 0, t 0, no metrics for that step
    k = horizon
    assert want[k - 1][2].all() and not want[k][2].any()
    assert envs.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP


def test_vector_env_same_step_autoreset_and_task_draws():
    n = 6
    envs = ga.GymNavVectorEnv(n, "restaurant", autoreset_mode=AutoresetMode.SAME_STEP)
    obs0, info = envs.reset(seed=3)
    again = ga.GymNavVectorEnv(n, "restaurant", autoreset_mode="SameStep")
    np.testing.assert_array_equal(again.reset(seed=3)[1]["task"], info["task"])
    before = info["task"].copy()
    horizon = envs.horizon
    last = None
    for k, a in enumerate(_actions(horizon, seed=2, shape=(n, 2))):
        obs, reward, terminated, truncated, info = envs.step(a)
        if k < horizon - 1:
            assert not truncated.any() and "final_obs" not in info
            last = obs
    assert truncated.all() and info["_final_obs"].all()
    finals = np.stack(info["final_obs"])
    assert finals.shape == obs.shape and not np.allclose(finals, last)
    assert np.all(info["t"] == 0)  # already reset: obs are the new episodes' first
    after = info["task"]
    assert not np.array_equal(after, before)  # each autoreset draws a task anew
    fresh = ga.GymNavVectorEnv(n, "restaurant", split="train", task=after)
    np.testing.assert_allclose(obs, fresh.reset(seed=0)[0], atol=1e-6)


def test_make_vec_render_and_registration():
    assert set(ga.ENV_IDS.values()) <= set(gym.registry)
    envs = gym.make_vec(SIDEWALK, num_envs=3, render_mode="rgb_array")
    assert isinstance(envs.unwrapped, ga.GymNavVectorEnv) and envs.num_envs == 3
    assert envs.single_observation_space.shape == (13,)
    assert envs.observation_space.shape == (3, 13) and envs.action_space.shape == (3, 2)
    envs.reset(seed=0)
    envs.step(envs.action_space.sample())
    frames = envs.render()
    assert len(frames) == 3 and all(f.dtype == np.uint8 and f.ndim == 3 for f in frames)
    with pytest.raises(ValueError, match="actions must have shape"):
        envs.step(np.zeros((2, 2), np.float32))
    # "module:id" imports the module that registers the ids
    env = gym.make("mpcpearl_jax.envs.gymnasium_adapter:mpcpearl_jax/Sidewalk-v0")
    assert env.unwrapped.nav.name == "sidewalk" and env.metadata["render_fps"] == 25
    from mpcpearl_jax.envs import GymNavEnv  # the lazy name of the package

    assert GymNavEnv is ga.GymNavEnv


def test_the_core_package_does_not_import_gymnasium():
    code = (
        "import sys\n"
        "import mpcpearl_jax, mpcpearl_jax.envs\n"
        "assert 'gymnasium' not in sys.modules\n"
        "import mpcpearl_jax.envs.gymnasium_adapter\n"
        "import gymnasium\n"
        "assert 'mpcpearl_jax/Restaurant-v0' in gymnasium.registry\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]


def test_without_gymnasium_the_module_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "gymnasium", None)  # `import gymnasium` raises ImportError
    monkeypatch.delitem(sys.modules, "mpcpearl_jax.envs.gymnasium_adapter", raising=False)
    with pytest.raises(ImportError) as e:
        importlib.import_module("mpcpearl_jax.envs.gymnasium_adapter")
    assert 'pip install -e ".[gymnasium]"' in str(e.value) and "\n" not in str(e.value)


def test_the_example_runs(tmp_path, capsys):
    from examples import gymnasium_random

    frame = tmp_path / "frame.png"
    gymnasium_random.main(["--num-envs", "3", "--vector-steps", "85", "--frame", str(frame)])
    out = capsys.readouterr().out
    assert "mpcpearl_jax/Restaurant-v0: task" in out and "80 steps" in out
    assert "3 episode(s) ended (autoreset)" in out
    assert frame.stat().st_size > 1000
