"""Shared drawing of tasks and robot paths (matplotlib, Agg backend): the one home of it.

The default figure, like the paper's: the arena, static obstacles in blue (a disc for a round
table, lo == hi; a rounded or plain rectangle for a box), people's paths in red where present,
one or more robot paths with labels, real collisions as stars, the start and the goal. Works for
any task family built on `TaskParams`; a family with its own style registers a viewer
(`envs.register(..., viewer=)`) built on these pieces, and `envs.save_trajectory` picks it.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, FancyBboxPatch, Rectangle  # noqa: E402

from mpcpearl_jax.envs.types import NavConfig, TaskParams  # noqa: E402

OBSTACLE_COLOR = "tab:blue"
HUMAN_COLOR = "tab:red"
ROBOT_COLORS = ("black", "tab:green", "tab:purple", "tab:orange", "tab:brown", "tab:cyan")


def _draw_arena(ax, cfg: NavConfig) -> None:
    lo, hi = np.asarray(cfg.arena_lo), np.asarray(cfg.arena_hi)
    ax.add_patch(Rectangle(lo, *(hi - lo), fill=False, edgecolor="0.3", lw=1.5))
    ax.set_xlim(lo[0] - 0.2, hi[0] + 0.2)
    ax.set_ylim(lo[1] - 0.2, hi[1] + 0.2)
    ax.set_aspect("equal")


def _draw_static(ax, params: TaskParams, cfg: NavConfig) -> None:
    """Static obstacles from lo [S, 2], hi [S, 2], radius [S], clipped to the arena."""
    a_lo, a_hi = np.asarray(cfg.arena_lo), np.asarray(cfg.arena_hi)
    los, his = np.asarray(params.static_lo), np.asarray(params.static_hi)
    for lo, hi, r in zip(los, his, np.asarray(params.static_radius), strict=True):
        style = dict(facecolor=OBSTACLE_COLOR, edgecolor="navy", alpha=0.6, zorder=1)
        if np.allclose(lo, hi):
            ax.add_patch(Circle(lo, r, **style))
            continue
        lo, hi = np.maximum(lo, a_lo - r), np.minimum(hi, a_hi + r)
        if r > 0:
            box = f"round,pad={r},rounding_size={r}"
            ax.add_patch(FancyBboxPatch(lo, *(hi - lo), boxstyle=box, **style))
        else:
            ax.add_patch(Rectangle(lo, *(hi - lo), **style))


def _draw_people(ax, params: TaskParams, cfg: NavConfig) -> None:
    """People's paths [T + 1, H, 2] in red, only where present; a dot at their last position."""
    pos, mask = np.asarray(params.human_pos), np.asarray(params.human_mask, bool)
    for h in range(pos.shape[1]):
        path = np.where(mask[:, h, None], pos[:, h], np.nan)  # gaps where absent
        label = "people" if h == 0 else None
        ax.plot(path[:, 0], path[:, 1], "-", color=HUMAN_COLOR, lw=1.0, alpha=0.8, label=label)
        present = np.flatnonzero(mask[:, h])
        if present.size:
            last = pos[present[-1], h]
            ax.add_patch(Circle(last, cfg.human_radius, color=HUMAN_COLOR, alpha=0.35, zorder=2))


def draw_robot_path(
    ax, label: str, positions, collisions, color: str, star_color: str = "gold"
) -> None:
    """One robot path positions [T + 1, 2]; collisions [T] bool starred at the blocked pose."""
    p = np.asarray(positions, dtype=float)
    ax.plot(p[:, 0], p[:, 1], "-", color=color, lw=2.0, zorder=3, label=label)
    ax.plot(p[-1, 0], p[-1, 1], "o", color=color, ms=5, zorder=3)
    if collisions is None:
        return
    hit = np.asarray(collisions, bool)
    if hit.shape[0] != p.shape[0] - 1:
        raise ValueError(f"collisions for {label!r} must have shape [{p.shape[0] - 1}]")
    where = p[1:][hit]
    if len(where):
        ax.scatter(
            where[:, 0],
            where[:, 1],
            marker="*",
            s=180,
            color=star_color,
            zorder=4,
            edgecolors="k",
            linewidths=0.6,
        )


def _draw_start_goal(ax, params: TaskParams, cfg: NavConfig) -> None:
    start, goal = np.asarray(params.start), np.asarray(params.goal)
    ax.plot(*start[:2], "s", color="k", ms=8, zorder=5, label="start")
    ax.add_patch(
        Circle(goal, cfg.goal_radius, facecolor="none", edgecolor="k", hatch="///", zorder=5)
    )
    ax.plot(*goal, "x", color="k", ms=8, zorder=5, label="goal")


def plot_episode(
    params: TaskParams,
    robot_paths: Mapping[str, np.ndarray],
    collisions: Mapping[str, np.ndarray] | None = None,
    config: NavConfig | None = None,
    title: str | None = None,
    ax=None,
):
    """Draw one task and the robot paths on `ax` (a new figure if None). Returns the figure.

    Args:
      params: single-task params.
      robot_paths: label -> positions [T + 1, 2].
      collisions: label -> bool [T], a real collision on that step (starred).
      config: the family's config (arena, radii); the restaurant defaults if None.
    """
    if params.start.ndim != 1:
        raise ValueError("plot_episode takes one task; index stacked params first")
    cfg = config or NavConfig()
    fig = ax.figure if ax is not None else plt.figure(figsize=(5.5, 5.5))
    ax = ax if ax is not None else fig.add_subplot(1, 1, 1)
    _draw_arena(ax, cfg)
    _draw_static(ax, params, cfg)
    _draw_people(ax, params, cfg)
    for i, (label, path) in enumerate(robot_paths.items()):
        hits = None if collisions is None else collisions.get(label)
        draw_robot_path(ax, label, path, hits, ROBOT_COLORS[i % len(ROBOT_COLORS)])
    _draw_start_goal(ax, params, cfg)
    ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    if title:
        ax.set_title(title)
    return fig


@contextmanager
def written_whole(path: str | Path) -> Iterator[Path]:
    """Yield a temporary name in `path`'s folder (same suffix, so writers pick the format from
    it) and rename it to `path` once the block ends without error: a stop signal or a full disk
    part-way leaves the previous file (or none), never a cut-short one under its name."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def save_figure(fig, path: str | Path, **savefig_kwargs) -> Path:
    """`fig.savefig(path, **savefig_kwargs)` written whole (`written_whole`); the bytes are those
    savefig writes."""
    with written_whole(path) as tmp:
        fig.savefig(tmp, **savefig_kwargs)
    return Path(path)


def save_trajectory_figure(
    path: str | Path,
    params: TaskParams,
    robot_paths: Mapping[str, np.ndarray],
    collisions: Mapping[str, np.ndarray] | None = None,
    config: NavConfig | None = None,
    title: str | None = None,
    dpi: int = 120,
) -> Path:
    """`plot_episode` saved as a PNG at `path` (parent folders created). Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = plot_episode(params, robot_paths, collisions, config, title)
    try:
        save_figure(fig, path, dpi=dpi, bbox_inches="tight")
    finally:
        plt.close(fig)
    return path


def save_robots_figure(
    path: str | Path,
    params: TaskParams,
    robots: Mapping[str, tuple[np.ndarray, np.ndarray | None]],
    config: NavConfig,
    title: str | None = None,
) -> Path:
    """The default viewer of the env registry: robots maps name -> (positions [T + 1, 2],
    collisions [T] or None)."""
    paths = {k: np.asarray(v[0]) for k, v in robots.items()}
    hits = {k: np.asarray(v[1]) for k, v in robots.items() if v[1] is not None}
    return save_trajectory_figure(path, params, paths, hits, config, title)
