"""The navigation tasks as Gymnasium envs, stepped with random actions.

    pip install -e ".[gymnasium]"
    python -m examples.gymnasium_random                      # the restaurant, one episode
    python -m examples.gymnasium_random --env sidewalk --num-envs 16 --frame frame.png

Importing `mpcpearl_jax.envs.gymnasium_adapter` registers "mpcpearl_jax/Restaurant-v0" and
"mpcpearl_jax/Sidewalk-v0"; `gymnasium.make` gives one env (a task of the training split drawn on
each reset), `gymnasium.make_vec` a batch of them stepped in one jitted call.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

from mpcpearl_jax.envs import gymnasium_adapter

IDS = gymnasium_adapter.ENV_IDS


def run_episode(env_id: str, seed: int, frame: str | None = None) -> dict:
    """One episode of random actions; returns its return, length and events."""
    env = gym.make(env_id, render_mode="rgb_array" if frame else None)
    env.action_space.seed(seed)
    obs, info = env.reset(seed=seed)
    total, steps, collisions, done = 0.0, 0, 0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        total, steps, collisions = total + reward, steps + 1, collisions + info["collision"]
        done = terminated or truncated
    if frame:
        import matplotlib.pyplot as plt

        plt.imsave(frame, env.render())
    env.close()
    return dict(task=info["task"], steps=steps, ret=total, collisions=collisions)


def run_vector(env_id: str, num_envs: int, steps: int, seed: int) -> dict:
    """`steps` calls of a vector env of `num_envs` slots (autoreset); returns its totals."""
    envs = gym.make_vec(env_id, num_envs=num_envs)
    envs.action_space.seed(seed)
    envs.reset(seed=seed)
    total, ended = np.zeros(num_envs), 0
    for _ in range(steps):
        _, reward, terminated, truncated, _ = envs.step(envs.action_space.sample())
        total += reward
        ended += int(np.sum(terminated | truncated))
    envs.close()
    return dict(mean_reward=float(total.mean() / steps), episodes_ended=ended)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", choices=sorted(IDS), default="restaurant")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--num-envs", type=int, default=8, help="slots of the vector env")
    p.add_argument("--vector-steps", type=int, default=100, help="calls of the vector env")
    p.add_argument("--frame", help="save the episode's last frame as this PNG")
    args = p.parse_args(argv)
    ep = run_episode(IDS[args.env], args.seed, args.frame)
    print(
        f"{IDS[args.env]}: task {ep['task']}, {ep['steps']} steps, return {ep['ret']:.2f}, "
        f"{ep['collisions']} collision(s)" + (f"; last frame in {args.frame}" if args.frame else "")
    )
    vec = run_vector(IDS[args.env], args.num_envs, args.vector_steps, args.seed)
    print(
        f"vector env, {args.num_envs} slots x {args.vector_steps} steps: mean reward per step "
        f"{vec['mean_reward']:.3f}, {vec['episodes_ended']} episode(s) ended (autoreset)"
    )


if __name__ == "__main__":
    main()
