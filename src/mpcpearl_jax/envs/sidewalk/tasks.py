"""Sidewalk tasks (method §4): static boxes, and people from a trajectory file or a synthetic crowd.

`make_sidewalk_tasks(split, seed, config, data=PATH)` builds stacked `TaskParams`:

* with `data` (an ETH/UCY file, e.g. UCY Zara 01): one task per full 10-second window of the scene
  (see `loader`). The split is fixed, not seeded: the test windows are every fifth full window
  starting from the third (indices 2, 7, 12, ...), spread over the whole scene; the others are
  training windows. Zara 01 has 31 full windows -> 25 train, 6 test (indices 2, 7, 12, 17, 22, 27).
  Split "ood" gives the windows that are *not* full (they contain stretches with nobody annotated;
  5 in Zara 01), which no other split uses.
* without `data`: a synthetic crowd (see `synthetic`), 25 train / 6 test windows drawn from
  independent seeded streams; "ood" is 6 windows of a faster, denser crowd.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from mpcpearl_jax.envs.sidewalk import loader
from mpcpearl_jax.envs.sidewalk.synthetic import SyntheticCrowd, synthetic_window
from mpcpearl_jax.envs.types import NavConfig, TaskParams, stack_params

NUM_HUMANS = 5
START = (1.0, 6.0, 0.0)
GOAL = (14.0, 5.0)
TEST_EVERY, TEST_OFFSET = 5, 2
NUM_SYNTHETIC = {"train": 25, "test": 6, "ood": 6}
OOD_CROWD = SyntheticCrowd(
    candidates=13, speed_median=1.5, speed_spread=0.2, speed_range=(0.9, 2.1)
)
# Extent that stands in for "unbounded" in the box edges: far outside any arena, small enough that
# float32 keeps centimetre resolution on it (spacing at 1e3 is 6e-5 m).
FAR = 1.0e3


def sidewalk_boxes(cfg: NavConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Static obstacles as plain boxes (radius 0): building, car 1, car 2, road (method §4).

    Returns lo [4, 2], hi [4, 2], radius [4] (float32). Half-infinite sides end FAR metres
    beyond the arena.
    """
    (x_lo, y_lo), (x_hi, y_hi) = cfg.arena_lo, cfg.arena_hi
    lo = [(x_lo - FAR, 7.0), (9.8, 10.2), (9.9, 5.5), (x_lo - FAR, y_lo - FAR)]
    hi = [(9.5, y_hi + FAR), (11.7, y_hi + FAR), (11.9, 10.3), (x_hi + FAR, 1.9)]
    return (
        np.asarray(lo, np.float32),
        np.asarray(hi, np.float32),
        np.zeros(len(lo), np.float32),
    )


def build_task(human_pos: np.ndarray, human_mask: np.ndarray, cfg: NavConfig) -> TaskParams:
    """One task from people positions [T + 1, H, 2] and presence [T + 1, H]."""
    lo, hi, radius = sidewalk_boxes(cfg)
    return TaskParams(
        human_pos=jnp.asarray(human_pos, jnp.float32),
        human_mask=jnp.asarray(human_mask, bool),
        static_lo=jnp.asarray(lo),
        static_hi=jnp.asarray(hi),
        static_radius=jnp.asarray(radius),
        start=jnp.asarray(START, jnp.float32),
        goal=jnp.asarray(GOAL, jnp.float32),
    )


def split_indices(num_windows: int) -> dict[str, np.ndarray]:
    """Which full windows are test (every fifth from the third) and which are train."""
    idx = np.arange(num_windows)
    is_test = (idx % TEST_EVERY) == TEST_OFFSET
    return {"train": idx[~is_test], "test": idx[is_test]}


def split_window_starts(scene: loader.Scene, split: str, cfg: NavConfig) -> np.ndarray:
    """Start frames [N] of the windows of a split, in task order."""
    full = loader.full_window_starts(scene, cfg.horizon, cfg.dt)
    if split == "ood":
        starts = loader.window_starts(scene, cfg.horizon, cfg.dt)
        return starts[~np.isin(starts, full)]
    return full[split_indices(len(full))[split]]


def task_windows(split: str, data: str | Path, cfg: NavConfig) -> np.ndarray:
    """Start times in seconds [N] of the windows behind `make_sidewalk_tasks(split, data=...)`."""
    scene = loader.load_eth_ucy(data)
    return split_window_starts(scene, split, cfg) / scene.fps


def data_tasks(
    split: str, data: str | Path, cfg: NavConfig, num_humans: int = NUM_HUMANS
) -> TaskParams:
    """Stacked tasks from an ETH/UCY file (one per window of the split)."""
    scene = loader.load_eth_ucy(data)
    loader.check_in_arena(scene, cfg.arena_lo, cfg.arena_hi)
    starts = split_window_starts(scene, split, cfg)
    if starts.size == 0:
        raise ValueError(
            f"{data}: no {split!r} windows of {cfg.horizon * cfg.dt:g} s in this scene "
            f"(span {scene.span_seconds:g} s)"
        )
    tasks = []
    for start in starts:
        ids, pos, mask = loader.window_tracks(scene, start, cfg.horizon, cfg.dt)
        _, pos, mask = loader.select_longest(ids, pos, mask, num_humans, cfg.arena_lo)
        tasks.append(build_task(pos, mask, cfg))
    return stack_params(tasks)


def synthetic_tasks(
    split: str, seed: int, cfg: NavConfig, crowd: SyntheticCrowd, num_humans: int = NUM_HUMANS
) -> TaskParams:
    """Stacked synthetic tasks; each split draws from its own seeded stream."""
    stream = {"train": 0, "test": 1, "ood": 2}[split]
    rng = np.random.default_rng(np.random.SeedSequence([seed, 4242, stream]))
    if split == "ood":
        crowd = dataclasses.replace(OOD_CROWD, lane_lo=crowd.lane_lo, lane_hi=crowd.lane_hi)
    x_range = (cfg.arena_lo[0], cfg.arena_hi[0])
    tasks = []
    for _ in range(NUM_SYNTHETIC[split]):
        ids, pos, mask = synthetic_window(rng, cfg.horizon, cfg.dt, x_range, crowd)
        _, pos, mask = loader.select_longest(ids, pos, mask, num_humans, cfg.arena_lo)
        tasks.append(build_task(pos, mask, cfg))
    return stack_params(tasks)


def make_sidewalk_tasks(
    split: str,
    seed: int,
    cfg: NavConfig,
    data: str | Path | None = None,
    crowd: SyntheticCrowd | None = None,
    num_humans: int = NUM_HUMANS,
) -> TaskParams:
    """Stacked sidewalk tasks of a split ("train", "test" or "ood").

    Args:
      data: an ETH/UCY trajectory file; None uses the synthetic crowd. With data the windows are
        fixed and `seed` is unused.
      crowd: synthetic crowd parameters (only without data).
      num_humans: pedestrians kept per window (H).
    Returns:
      TaskParams with a leading task axis: human_pos [N, T + 1, H, 2], human_mask [N, T + 1, H],
      four boxes, start (1, 6, 0), goal (14, 5).
    """
    if split not in NUM_SYNTHETIC:
        raise ValueError(f"unknown split {split!r}; expected one of {tuple(NUM_SYNTHETIC)}")
    if data is not None:
        if crowd is not None:
            raise TypeError("make_sidewalk_tasks: give either data or crowd, not both")
        return data_tasks(split, data, cfg, num_humans)
    return synthetic_tasks(split, seed, cfg, crowd or SyntheticCrowd(), num_humans)
