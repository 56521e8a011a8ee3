"""A synthetic crowd on the sidewalk, the default when no trajectory file is given (method §4).

People walk along the sidewalk (the band between the road, y <= 1.9, and the parked car,
y >= 5.5) in both directions at about 1.15 m/s (the Zara 01 median), each with its own speed, lane
and a slight heading that makes it drift sideways; a drifting person bounces off the band edges so
nobody steps onto the road or into the car. People enter and leave through the ends of the arena
at random times, so presence masks vary within a window. Host-side NumPy, deterministic per seed.
The windows then go through the same selection as real data (`loader.select_longest`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mpcpearl_jax.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class SyntheticCrowd:
    """Parameters of the synthetic crowd (metres, seconds).

    `candidates` people are sampled per window; with entry times spread over `entry_window`
    seconds around the window's start, about 5 are in view at a time, as in Zara 01.
    """

    candidates: int = 9
    speed_median: float = 1.15
    speed_spread: float = 0.15  # standard deviation before clipping
    speed_range: tuple[float, float] = (0.7, 1.7)
    heading_spread: float = 0.08  # radians, std of the walking direction around +-x
    lane_lo: float = 2.3  # band of walking centres, clear of the road and the car by > r_d
    lane_hi: float = 5.1
    entry_window: tuple[float, float] = (-12.0, 9.0)  # entry time relative to the window start

    def __post_init__(self) -> None:
        n = type(self).__name__
        if not (isinstance(self.candidates, int) and self.candidates > 0):
            raise ConfigError(f"{n}.candidates: must be a positive int, got {self.candidates!r}")
        if not (0 < self.speed_range[0] <= self.speed_median <= self.speed_range[1]):
            raise ConfigError(f"{n}.speed_median: must lie inside speed_range {self.speed_range}")
        if not self.lane_lo < self.lane_hi:
            raise ConfigError(f"{n}.lane_hi: must exceed lane_lo ({self.lane_lo})")
        if not self.entry_window[0] < self.entry_window[1]:
            raise ConfigError(f"{n}.entry_window: must be an increasing pair")


def reflect(y: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Fold values into [lo, hi] by mirror reflection at the edges (same shape as y)."""
    width = hi - lo
    z = np.mod(y - lo, 2.0 * width)
    return lo + np.where(z > width, 2.0 * width - z, z)


def sample_walkers(rng: np.random.Generator, crowd: SyntheticCrowd) -> dict[str, np.ndarray]:
    """Per-person walking parameters, each [C]: direction (+-1), speed, heading, lane, entry."""
    c = crowd.candidates
    speed = np.clip(rng.normal(crowd.speed_median, crowd.speed_spread, c), *crowd.speed_range)
    return dict(
        direction=rng.choice(np.array([-1.0, 1.0]), size=c),
        speed=speed,
        heading=rng.normal(0.0, crowd.heading_spread, c),
        lane=rng.uniform(crowd.lane_lo, crowd.lane_hi, c),
        entry=rng.uniform(*crowd.entry_window, c),
    )


def walk(
    walkers: dict[str, np.ndarray],
    times: np.ndarray,
    x_range: tuple[float, float],
    crowd: SyntheticCrowd,
) -> tuple[np.ndarray, np.ndarray]:
    """Positions [Q, C, 2] and presence [Q, C] of the walkers at `times` [Q] (seconds).

    A person enters at one end of `x_range` at its entry time, walks straight with constant
    speed (bouncing between the lane edges when it drifts) and is present until it leaves
    at the other end; absent people are held at their entry or exit point.
    """
    vx = walkers["speed"] * np.cos(walkers["heading"])
    vy = walkers["speed"] * np.sin(walkers["heading"])
    crossing = (x_range[1] - x_range[0]) / vx  # seconds inside the arena [C]
    tau = times[:, None] - walkers["entry"][None, :]  # time since entry [Q, C]
    present = (tau >= 0.0) & (tau <= crossing)
    tau = np.clip(tau, 0.0, crossing)  # absent people wait at their entry / exit point
    x0 = np.where(walkers["direction"] > 0, x_range[0], x_range[1])
    x = x0 + walkers["direction"] * vx * tau
    y = reflect(walkers["lane"] + vy * tau, crowd.lane_lo, crowd.lane_hi)
    return np.stack([x, y], axis=-1), present


def synthetic_window(
    rng: np.random.Generator,
    horizon: int,
    dt: float,
    x_range: tuple[float, float],
    crowd: SyntheticCrowd,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One synthetic window: ids [C], positions [T + 1, C, 2], presence [T + 1, C]."""
    walkers = sample_walkers(rng, crowd)
    pos, mask = walk(walkers, dt * np.arange(horizon + 1), x_range, crowd)
    return np.arange(crowd.candidates), pos, mask
