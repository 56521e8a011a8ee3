"""ETH/UCY pedestrian trajectory files and their 10-second windows (method §4).

The common text format has one row per annotated position, with no header::

    frame_id  pedestrian_id  x  y        (whitespace or tab separated, x and y in metres)

Frames are numbered in the original 25 fps video and annotated every 10 frames (2.5 Hz).

Windowing (what the sidewalk tasks are made of):
  * the scene is cut into consecutive, non-overlapping windows of `horizon * dt` seconds
    (250 steps x 0.04 s = 10 s = 250 video frames), the first starting at the first frame;
  * a window is *full* when every annotation frame inside it (both ends included) is in the file.
    Frames with nobody in view are missing from the file, so windows that contain such holes are
    set aside (for Zara 01: 36 windows, 31 full);
  * each pedestrian is linearly interpolated to the env's time grid, *only inside its observed
    span* (and not across a hole in its own track); outside it the person is absent;
  * each window keeps the `num_humans` pedestrians present for the most steps (ties: smaller id),
    longest first, with a presence mask; empty slots are absent throughout.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from mpcpearl_jax.errors import DataFormatError

VIDEO_FPS = 25.0  # ETH/UCY frame numbers count frames of a 25 fps video
# the largest frame number and pedestrian id read: 10^8 frames are 46 days of 25 fps video (the
# UCY and ETH files stay below 10^5); beyond, a window count or an id would not fit in memory or
# in an int64
MAX_FRAME = 10**8
MAX_PED_ID = 10**9
NUM_COLUMNS = 4


__all__ = ["DataFormatError"]  # re-exported from mpcpearl_jax.errors, its home


@dataclasses.dataclass(frozen=True)
class Scene:
    """One ETH/UCY scene, rows sorted by (pedestrian, frame).

    Attributes:
      path: the file it came from.
      frame: [N] int64 video frame of each row.
      ped_id: [N] int64 pedestrian id of each row.
      xy: [N, 2] float64 position in metres.
      fps: video frame rate (frames per second).
    """

    path: str
    frame: np.ndarray
    ped_id: np.ndarray
    xy: np.ndarray
    fps: float = VIDEO_FPS

    @property
    def pedestrians(self) -> np.ndarray:
        """Sorted distinct pedestrian ids [P]."""
        return np.unique(self.ped_id)

    @property
    def num_pedestrians(self) -> int:
        return int(self.pedestrians.size)

    @property
    def annotated_frames(self) -> np.ndarray:
        """Sorted distinct frames that hold at least one row [F]."""
        return np.unique(self.frame)

    @property
    def frame_step(self) -> int:
        """Frames between two annotations (the most common gap between annotated frames)."""
        gaps = np.diff(self.annotated_frames)
        if gaps.size == 0:
            return 1
        values, counts = np.unique(gaps, return_counts=True)
        return int(values[np.argmax(counts)])

    @property
    def span_seconds(self) -> float:
        """Time from the first to the last annotated frame."""
        f = self.annotated_frames
        return float(f[-1] - f[0]) / self.fps

    def track(self, ped: int) -> tuple[np.ndarray, np.ndarray]:
        """Frames [n] and positions [n, 2] of one pedestrian, in time order."""
        sel = self.ped_id == ped
        return self.frame[sel], self.xy[sel]


# --------------------------------------------------------------------------- parsing
def _parse_line(path: Path, lineno: int, line: str) -> tuple[float, float, float, float]:
    fields = line.split()
    if len(fields) != NUM_COLUMNS:
        raise DataFormatError(
            f"{path}: line {lineno}: expected {NUM_COLUMNS} columns (frame, pedestrian id, x, y), "
            f"got {len(fields)}"
        )
    values = []
    for tok in fields:
        try:
            v = float(tok)
        except ValueError:
            raise DataFormatError(f"{path}: line {lineno}: non-numeric value {tok!r}") from None
        if not math.isfinite(v):
            raise DataFormatError(f"{path}: line {lineno}: non-finite value {tok!r}")
        values.append(v)
    frame, ped = values[0], values[1]
    if frame != round(frame) or ped != round(ped):
        raise DataFormatError(
            f"{path}: line {lineno}: frame and pedestrian id must be whole numbers, "
            f"got {fields[:2]}"
        )
    if abs(frame) > MAX_FRAME:
        raise DataFormatError(
            f"{path}: line {lineno}: frame {fields[0]} is beyond {MAX_FRAME:,} (46 days of "
            f"{VIDEO_FPS:g} fps video); frames must be the video's frame numbers"
        )
    if abs(ped) > MAX_PED_ID:
        raise DataFormatError(
            f"{path}: line {lineno}: pedestrian id {fields[1]} is beyond {MAX_PED_ID:,}"
        )
    return values[0], values[1], values[2], values[3]


def load_eth_ucy(path: str | Path, fps: float = VIDEO_FPS) -> Scene:
    """Read an ETH/UCY trajectory file (blank lines and lines starting with '#' are skipped).

    Raises:
      FileNotFoundError: the file does not exist.
      DataFormatError: wrong column count, non-numeric or non-finite value, a frame beyond
        MAX_FRAME or a pedestrian id beyond MAX_PED_ID (with the line number), duplicate (frame,
        pedestrian) rows, no rows at all, or not a text file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    rows = []
    lineno = 0
    try:
        with path.open(encoding="utf-8") as fh:
            for lineno, line in enumerate(fh, start=1):
                if "\x00" in line:
                    raise DataFormatError(f"{path}: line {lineno}: NUL byte (not a text file)")
                if line.strip() and not line.lstrip().startswith("#"):
                    rows.append(_parse_line(path, lineno, line))
    except UnicodeDecodeError as e:
        raise DataFormatError(
            f"{path}: not a text trajectory file (undecodable byte after line {lineno})"
        ) from e
    if not rows:
        raise DataFormatError(f"{path}: empty scene (no trajectory rows)")
    data = np.asarray(rows, dtype=np.float64)
    frame, ped = data[:, 0].astype(np.int64), data[:, 1].astype(np.int64)
    order = np.lexsort((frame, ped))
    frame, ped, xy = frame[order], ped[order], data[order, 2:4]
    dup = (np.diff(frame) == 0) & (np.diff(ped) == 0)
    if np.any(dup):
        i = int(np.argmax(dup))
        raise DataFormatError(f"{path}: pedestrian {ped[i]} has two rows for frame {frame[i]}")
    return Scene(path=str(path), frame=frame, ped_id=ped, xy=xy, fps=fps)


# ------------------------------------------------------------------------- windowing
def check_in_arena(
    scene: Scene,
    arena_lo: tuple[float, float],
    arena_hi: tuple[float, float],
    margin: float = 1.0,
    min_share: float = 0.5,
) -> None:
    """DataFormatError naming the file unless at least `min_share` of its positions lie in the
    arena grown by `margin` metres: a file in other units (centimetres) or another frame (shifted
    by hundreds of metres) would otherwise train with every person outside the arena."""
    lo = np.asarray(arena_lo, np.float64) - margin
    hi = np.asarray(arena_hi, np.float64) + margin
    share = float(np.mean(np.all((scene.xy >= lo) & (scene.xy <= hi), axis=1)))
    if share < min_share:
        span = f"x {scene.xy[:, 0].min():.4g} to {scene.xy[:, 0].max():.4g}, y "
        span += f"{scene.xy[:, 1].min():.4g} to {scene.xy[:, 1].max():.4g}"
        raise DataFormatError(
            f"{scene.path}: only {share:.0%} of its positions ({span}) lie in the arena x "
            f"[{arena_lo[0]:g}, {arena_hi[0]:g}], y [{arena_lo[1]:g}, {arena_hi[1]:g}] (+- "
            f"{margin:g} m); positions must be metres in the arena's frame, as in UCY "
            "crowds_zara01.txt"
        )


def window_frames(scene: Scene, horizon: int, dt: float) -> float:
    """Length of one window (horizon * dt seconds) in video frames."""
    return horizon * dt * scene.fps


def window_starts(scene: Scene, horizon: int, dt: float) -> np.ndarray:
    """Start frames [W] of all consecutive windows that fit inside the scene."""
    length = window_frames(scene, horizon, dt)
    f = scene.annotated_frames
    count = int(math.floor((f[-1] - f[0]) / length + 1e-9))
    return f[0] + length * np.arange(count)


def is_full_window(scene: Scene, start: float, length: float) -> bool:
    """True when every annotation frame in [start, start + length] is present in the file."""
    step = scene.frame_step
    first = math.ceil((start - scene.annotated_frames[0]) / step - 1e-9)
    last = math.floor((start + length - scene.annotated_frames[0]) / step + 1e-9)
    expected = scene.annotated_frames[0] + step * np.arange(first, last + 1)
    return bool(np.all(np.isin(expected, scene.annotated_frames)))


def full_window_starts(scene: Scene, horizon: int, dt: float) -> np.ndarray:
    """Start frames [W_full] of the full windows, in time order."""
    length = window_frames(scene, horizon, dt)
    starts = window_starts(scene, horizon, dt)
    return np.asarray([s for s in starts if is_full_window(scene, s, length)])


def interpolate_track(
    frames: np.ndarray, xy: np.ndarray, query: np.ndarray, max_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of one track at query frames.

    Args:
      frames: [n] increasing frames of the samples; xy: [n, 2] positions.
      query: [Q] frames to evaluate; max_gap: samples further apart than this are not joined.
    Returns:
      positions [Q, 2] (outside the observed span: the nearest end is held) and presence [Q] bool,
      True only inside the span and not inside a gap longer than `max_gap`.
    """
    pos = np.stack([np.interp(query, frames, xy[:, k]) for k in range(2)], axis=-1)
    inside = (query >= frames[0]) & (query <= frames[-1])
    right = np.clip(np.searchsorted(frames, query, side="left"), 1, max(len(frames) - 1, 1))
    left = right - 1
    gap = frames[right] - frames[left] if len(frames) > 1 else np.zeros_like(query)
    on_sample = np.isin(query, frames)
    return pos, inside & ((gap <= max_gap) | on_sample)


def window_tracks(
    scene: Scene, start: float, horizon: int, dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All pedestrians seen in a window, interpolated to the env grid.

    Returns:
      ids [P], positions [T + 1, P, 2], presence [T + 1, P] bool (P = people present at least
      one step).
    """
    query = start + dt * scene.fps * np.arange(horizon + 1)
    max_gap = scene.frame_step + 1e-6
    ids, pos, mask = [], [], []
    for ped in scene.pedestrians:
        frames, xy = scene.track(int(ped))
        if frames[-1] < query[0] or frames[0] > query[-1]:
            continue
        p, m = interpolate_track(frames.astype(np.float64), xy, query, max_gap)
        if m.any():
            ids.append(int(ped))
            pos.append(p)
            mask.append(m)
    if not ids:
        return (
            np.zeros(0, np.int64),
            np.zeros((horizon + 1, 0, 2)),
            np.zeros((horizon + 1, 0), bool),
        )
    return np.asarray(ids), np.stack(pos, axis=1), np.stack(mask, axis=1)


def select_longest(
    ids: np.ndarray, pos: np.ndarray, mask: np.ndarray, num: int, empty_xy: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the `num` people present for the most steps (ties: smaller id), longest first.

    Args:
      ids [P], pos [T + 1, P, 2], mask [T + 1, P]; empty_xy: position given to empty slots.
    Returns:
      ids [num] (-1 for an empty slot), pos [T + 1, num, 2], mask [T + 1, num].
    """
    order = np.lexsort((ids, -mask.sum(axis=0)))[:num]
    steps = pos.shape[0]
    out_ids = np.full(num, -1, np.int64)
    out_pos = np.broadcast_to(np.asarray(empty_xy, np.float64), (steps, num, 2)).copy()
    out_mask = np.zeros((steps, num), bool)
    k = order.size
    out_ids[:k], out_pos[:, :k], out_mask[:, :k] = ids[order], pos[:, order], mask[:, order]
    return out_ids, out_pos, out_mask
