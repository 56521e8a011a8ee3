"""Trajectory figures like the paper's: kept as a public name; the drawing lives in
`mpcpearl_jax.envs.drawing` (below the envs, so task families draw with it), and each family's
figure style is found through the env registry (`mpcpearl_jax.envs.save_trajectory`)."""

from mpcpearl_jax.envs.drawing import (
    HUMAN_COLOR,
    OBSTACLE_COLOR,
    ROBOT_COLORS,
    draw_robot_path,
    plot_episode,
    save_robots_figure,
    save_trajectory_figure,
)

__all__ = [
    "HUMAN_COLOR",
    "OBSTACLE_COLOR",
    "ROBOT_COLORS",
    "draw_robot_path",
    "plot_episode",
    "save_robots_figure",
    "save_trajectory_figure",
]
