"""Animated episodes as GIFs (matplotlib animation, Pillow writer; no other dependency).

One frame per step (or every few steps for long episodes): the arena, static obstacles, the people
as discs of their radius with a dashed safety ring (radius r_d + r_safe: the robot's body must stay
out of it, drawn solid while it does not), the robot as a disc of its radius with its heading and
its trail, the step counter, who acted on the step (policy or MPC, where known), and collisions
flashed (red frame, red robot, a star left where it happened). Works for any `TaskParams` family.

    animate_episode("episode.gif", task, env.config, positions, collisions, headings, acted_by)
    animate_result("episode.gif", result, tasks, env.config, task=0, seed=0)  # evaluator output
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import jax  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402

from mpcpearl_jax.envs import drawing  # noqa: E402
from mpcpearl_jax.envs.types import NavConfig, TaskParams  # noqa: E402

POLICY_COLOR = "0.6"
MPC_COLOR = "tab:orange"
COLLISION_COLOR = "red"
PEOPLE_TRAIL_STEPS = 8
# crisp shapes (no anti-aliasing) keep the GIF palette small: ~4x smaller files
_RC = {"patch.antialiased": False, "lines.antialiased": False, "hatch.linewidth": 0.6}


def frame_steps(horizon: int, max_frames: int) -> np.ndarray:
    """Steps shown: 0, stride, 2 stride, ... and always the last one (T), at most ~max_frames."""
    stride = max(1, math.ceil((horizon + 1) / max_frames))
    steps = np.arange(0, horizon + 1, stride)
    if steps[-1] != horizon:
        steps = np.append(steps, horizon)
    return steps


def headings_from_positions(positions: np.ndarray, start_heading: float) -> np.ndarray:
    """Heading [T + 1] from the direction of travel (kept while the robot does not move)."""
    d = np.diff(positions, axis=0)
    out = np.empty(len(positions))
    out[0] = start_heading
    for t, (dx, dy) in enumerate(d):
        out[t + 1] = math.atan2(dy, dx) if math.hypot(dx, dy) > 1e-6 else out[t]
    return out


def _actor_color(label: str) -> str:
    return MPC_COLOR if label.startswith("MPC") else POLICY_COLOR


def animate_episode(
    path: str | Path,
    task: TaskParams,
    config: NavConfig,
    positions,
    collisions=None,
    headings=None,
    acted_by: Sequence[str] | None = None,
    title: str | None = None,
    max_frames: int = 90,
    fps: int = 10,
    width_in: float = 4.2,
    dpi: int = 80,
) -> Path:
    """Write one episode as an animated GIF at `path`; returns the path.

    Args:
      task: the single task the episode ran on.
      positions: robot positions [T + 1, 2] (the start included).
      collisions: bool [T], a real collision on that step (the move was blocked).
      headings: robot heading [T + 1] in radians; from the direction of travel if None.
      acted_by: [T] who chose the action of each step, e.g. "policy" or "MPC" (MPC in orange).
      max_frames: at most about this many frames (long episodes show every k-th step).
      fps: GIF frames per second; width_in and dpi set the image size (default 336 px wide).
    """
    if task.start.ndim != 1:
        raise ValueError("animate_episode takes one task; index stacked params first")
    pos = np.asarray(positions, dtype=float)
    horizon = pos.shape[0] - 1
    col = np.zeros(horizon, bool) if collisions is None else np.asarray(collisions, bool)
    if col.shape != (horizon,):
        raise ValueError(f"collisions must have shape [{horizon}], got {col.shape}")
    head = (
        headings_from_positions(pos, float(np.asarray(task.start)[2]))
        if headings is None
        else np.asarray(headings, dtype=float)
    )
    if head.shape != (horizon + 1,):
        raise ValueError(f"headings must have shape [{horizon + 1}], got {head.shape}")
    if acted_by is not None and len(acted_by) != horizon:
        raise ValueError(f"acted_by must have {horizon} entries, got {len(acted_by)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    steps = frame_steps(horizon, max_frames)
    with matplotlib.rc_context(_RC):  # type: ignore[arg-type]  # keys typed as literals
        fig, draw = _figure(task, config, pos, col, head, acted_by, steps, title, width_in)
        # renamed once every frame is in: a stop or an error part-way leaves no GIF (or the
        # previous one), never a short one that looks whole
        try:
            with drawing.written_whole(path) as tmp:
                anim = FuncAnimation(fig, draw, frames=len(steps), blit=False)
                anim.save(tmp, writer=PillowWriter(fps=fps), dpi=dpi)
        finally:
            plt.close(fig)
    return path


def _figure(task, config, pos, col, head, acted_by, steps, title, width_in):
    """The figure with every artist, and draw(i) updating them to frame i (step steps[i])."""
    horizon = pos.shape[0] - 1
    humans = np.asarray(task.human_pos, dtype=float)
    present = np.asarray(task.human_mask, bool)

    lo, hi = np.asarray(config.arena_lo), np.asarray(config.arena_hi)
    aspect = (hi[1] - lo[1]) / (hi[0] - lo[0])
    header, footer = 0.42, 0.16  # inches above (title, step, actor) and below (events) the arena
    height = width_in * aspect + header + footer
    fig = plt.figure(figsize=(width_in, height))
    ax = fig.add_axes((0.01, footer / height, 0.98, width_in * aspect / height))
    ax.set_axis_off()
    drawing._draw_arena(ax, config)
    drawing._draw_static(ax, task, config)
    flash = Rectangle(lo, *(hi - lo), fill=False, edgecolor=COLLISION_COLOR, lw=4, zorder=8)
    flash.set_visible(False)
    ax.add_patch(flash)
    goal = np.asarray(task.goal)
    ax.add_patch(Circle(goal, config.goal_radius, facecolor="none", edgecolor="k", hatch="///"))
    ax.plot(*np.asarray(task.start)[:2], "s", color="k", ms=5, zorder=5)
    top = 1.0 - 0.06 / height
    if title:
        fig.text(0.5, top, title, fontsize=7.5, ha="center", va="top")
    line2 = 1.0 - 0.26 / height
    step_text = fig.text(0.03, line2, "", fontsize=7.5, va="top", family="monospace")
    actor_text = fig.text(0.97, line2, "", fontsize=7.5, va="top", ha="right", weight="bold")
    event_text = fig.text(0.03, 0.02 / height, "", fontsize=7.5, va="bottom", weight="bold")

    r_ring = config.human_radius + config.r_safe
    people = []
    for _ in range(humans.shape[1]):
        body = Circle((0, 0), config.human_radius, color=drawing.HUMAN_COLOR, alpha=0.55, zorder=3)
        ring = Circle((0, 0), r_ring, fill=False, color=drawing.HUMAN_COLOR, lw=0.8, ls="--")
        (trail,) = ax.plot([], [], "-", color=drawing.HUMAN_COLOR, lw=0.8, alpha=0.5, zorder=2)
        ax.add_patch(body)
        ax.add_patch(ring)
        people.append((body, ring, trail))
    (robot_trail,) = ax.plot([], [], "-", color="k", lw=1.4, zorder=4)
    (mpc_marks,) = ax.plot([], [], "o", color=MPC_COLOR, ms=2.5, zorder=4, ls="none")
    (stars,) = ax.plot([], [], "*", color="gold", ms=11, mec="k", mew=0.5, zorder=7, ls="none")
    robot = Circle((0, 0), config.robot_radius, facecolor=POLICY_COLOR, edgecolor="k", zorder=6)
    ax.add_patch(robot)
    (nose,) = ax.plot([], [], "-", color="k", lw=1.6, zorder=6.5)
    mpc_xy = np.full_like(pos, np.nan)
    if acted_by is not None:  # an MPC step is marked at the position it led to
        is_mpc = np.array([a.startswith("MPC") for a in acted_by])
        mpc_xy[1:][is_mpc] = pos[1:][is_mpc]
    hit_xy = np.full_like(pos, np.nan)
    hit_xy[1:][col] = pos[1:][col]

    def draw(i: int):
        t, prev = int(steps[i]), int(steps[max(i - 1, 0)])
        p = pos[t]
        for h, (body, ring, trail) in enumerate(people):
            here = bool(present[t, h])
            for artist in (body, ring, trail):
                artist.set_visible(here)
            if not here:
                continue
            body.center = humans[t, h]
            ring.center = humans[t, h]
            near = np.linalg.norm(p - humans[t, h]) < config.eps_dynamic
            ring.set_linestyle("-" if near else "--")
            ring.set_linewidth(1.4 if near else 0.8)
            t0 = max(0, t - PEOPLE_TRAIL_STEPS)
            seg = np.where(present[t0 : t + 1, h, None], humans[t0 : t + 1, h], np.nan)
            trail.set_data(seg[:, 0], seg[:, 1])
        robot_trail.set_data(pos[: t + 1, 0], pos[: t + 1, 1])
        mpc_marks.set_data(mpc_xy[: t + 1, 0], mpc_xy[: t + 1, 1])
        stars.set_data(hit_xy[: t + 1, 0], hit_xy[: t + 1, 1])
        robot.center = p
        tip = p + 1.5 * config.robot_radius * np.array([math.cos(head[t]), math.sin(head[t])])
        nose.set_data([p[0], tip[0]], [p[1], tip[1]])
        # what happened on the steps since the previous frame (prev, t]
        hit_now = bool(col[prev:t].any())
        actor = ""
        if acted_by is not None and t > 0:
            since = acted_by[prev:t]
            mpc = [a for a in since if a.startswith("MPC")]
            actor = mpc[-1] if mpc else since[-1]
        robot.set_facecolor(COLLISION_COLOR if hit_now else _actor_color(actor))
        flash.set_visible(hit_now)
        step_text.set_text(f"step {t:>{len(str(horizon))}}/{horizon}  t = {t * config.dt:5.2f} s")
        actor_text.set_text(actor)
        actor_text.set_color(_actor_color(actor))
        actor_text.set_visible(bool(actor))
        n_hits = int(col[:t].sum())
        in_goal = bool(np.linalg.norm(p - goal) <= config.goal_radius)
        parts = (["COLLISION"] if hit_now else []) + ([f"collisions: {n_hits}"] if n_hits else [])
        parts += ["in goal"] if in_goal else []
        event_text.set_text("  ".join(parts))
        event_text.set_color(COLLISION_COLOR if n_hits else "tab:green")
        event_text.set_visible(bool(parts))
        return ()

    return fig, draw


def animate_result(
    path: str | Path,
    result: dict,
    tasks: TaskParams,
    config: NavConfig,
    task: int = 0,
    seed: int = 0,
    title: str | None = None,
    **kwargs,
) -> Path:
    """GIF of one episode of a batch of results: arrays [S, N, ...] (seeds x tasks) with
    "position", "collision", "heading" as `evaluate.make_evaluator` returns them, and optionally
    "acted_by" [S, N, T] labels or "used_mpc" [S, N, T] (without either, the policy acted on
    every step: the meta-test protocol). task and seed index the N and S axes; tasks is [N]."""
    one = {k: np.asarray(v)[seed, task] for k, v in result.items() if np.ndim(v) >= 3}
    params = jax.tree_util.tree_map(lambda x: np.asarray(x)[task], tasks)
    horizon = one["position"].shape[0] - 1
    if "acted_by" in one:
        acted = [str(a) for a in one["acted_by"]]
    elif "used_mpc" in one:
        acted = ["MPC" if u else "policy" for u in one["used_mpc"]]
    else:
        acted = ["policy"] * horizon
    return animate_episode(
        path,
        params,
        config,
        one["position"],
        one.get("collision"),
        one.get("heading"),
        acted,
        title,
        **kwargs,
    )
