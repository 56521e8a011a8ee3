"""Sidewalk trajectory figure in the style of the paper's sidewalk figure.

Static obstacles are drawn as rectangles (clipped to the arena), pedestrian paths as orange
circles (only where present), each robot path as a line from the start to its end point, the goal
as a cross-hatched disc, and every real collision as a star.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mpcpearl_jax.envs.types import NavConfig, TaskParams

PEDESTRIAN_COLOR = "tab:orange"
ROBOT_COLORS = ("tab:blue", "tab:green", "tab:purple", "tab:red", "tab:brown", "tab:cyan")


def _draw_boxes(ax, params: TaskParams, cfg: NavConfig) -> None:
    from matplotlib.patches import Rectangle

    lo = np.maximum(np.asarray(params.static_lo), np.asarray(cfg.arena_lo))
    hi = np.minimum(np.asarray(params.static_hi), np.asarray(cfg.arena_hi))
    for a, b in zip(lo, hi, strict=True):
        ax.add_patch(Rectangle(a, *(b - a), facecolor="0.75", edgecolor="0.3", zorder=1))


def _draw_people(ax, params: TaskParams, stride: int) -> None:
    pos, mask = np.asarray(params.human_pos), np.asarray(params.human_mask)
    for h in range(pos.shape[1]):
        keep = mask[::stride, h]
        pts = pos[::stride, h][keep]
        ax.scatter(
            pts[:, 0],
            pts[:, 1],
            s=14,
            facecolors="none",
            edgecolors=PEDESTRIAN_COLOR,
            linewidths=0.8,
            zorder=2,
            label="pedestrians" if h == 0 else None,
        )


def plot_sidewalk(
    params: TaskParams,
    cfg: NavConfig,
    robots: Mapping[str, tuple[np.ndarray, np.ndarray | None]],
    path: str | Path | None = None,
    title: str | None = None,
    stride: int = 10,
):
    """Draw one sidewalk task with one or more robot paths; save a PNG when `path` is given.

    Args:
      params: a single task.
      robots: name -> (positions [T + 1, 2], collisions [T] bool or None), e.g. from
        `NavEnv.rollout` ("position", "collision").
      stride: draw every stride-th pedestrian position (10 = 2.5 Hz at dt 0.04).
    Returns:
      the matplotlib Figure.
    """
    from matplotlib.figure import Figure

    from mpcpearl_jax.envs.drawing import draw_robot_path, save_figure

    fig = Figure(figsize=(6.4, 5.4))
    ax = fig.add_subplot()
    _draw_boxes(ax, params, cfg)
    _draw_people(ax, params, stride)
    start, goal = np.asarray(params.start), np.asarray(params.goal)
    ax.plot(*start[:2], "ks", ms=7, zorder=5, label="start")
    ax.add_patch(_goal_patch(goal, cfg.goal_radius))
    for i, (name, (positions, collisions)) in enumerate(robots.items()):
        color = ROBOT_COLORS[i % len(ROBOT_COLORS)]
        draw_robot_path(ax, name, positions, collisions, color, star_color="red")
    ax.set_xlim(cfg.arena_lo[0], cfg.arena_hi[0])
    ax.set_ylim(cfg.arena_lo[1], cfg.arena_hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if title:
        ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    if path is not None:
        save_figure(fig, path, dpi=120, bbox_inches="tight")
    return fig


def _goal_patch(goal: np.ndarray, radius: float):
    from matplotlib.patches import Circle

    return Circle(
        (float(goal[0]), float(goal[1])),
        radius,
        facecolor="none",
        edgecolor="k",
        hatch="//",
        zorder=5,
    )
