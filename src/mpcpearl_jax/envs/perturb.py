"""Crowd perturbations for evaluation: the people's paths kept, their timing changed.

A trained policy should react to the people it sees, not to the timetable of its training crowds.
`perturb_tasks` re-times the precomputed paths of any task set (generated restaurant crowds, the
paper's scenarios, sidewalk windows), on the task arrays alone:

- `delay=K` (steps, K >= 0): every person holds its step-0 position (and presence) for K more
  steps, then follows its path; the last K steps of the original path are cut off.
      new[t] = old[max(t - K, 0)]
- `speed=S` (S > 0): the path is followed S times as fast (S < 1 slower), the person standing at
  its last position once the path is used up:
      new[t] = old(min(S t, T)), linearly interpolated between steps
  A person is present at a fractional time only if present at both neighbouring steps.
- both: the path is re-timed by `speed`, then delayed by `delay`.

The robot's start, the goal and the static obstacles are unchanged. Pure JAX: jit- and
vmap-friendly, with a leading task axis or without one.
"""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs.types import TaskParams

MAX_DELAY = 10_000  # steps; beyond any episode length here


@dataclasses.dataclass(frozen=True)
class Perturbation:
    """How the crowd's timing is changed: `delay` steps of waiting, paths at `speed` times."""

    delay: int = 0
    speed: float = 1.0

    def __post_init__(self) -> None:
        if isinstance(self.delay, bool) or not isinstance(self.delay, int):
            raise ValueError(f"perturbation delay: must be an int of steps, got {self.delay!r}")
        if not 0 <= self.delay <= MAX_DELAY:
            raise ValueError(f"perturbation delay: must be in [0, {MAX_DELAY}], got {self.delay}")
        ok = isinstance(self.speed, (int, float)) and not isinstance(self.speed, bool)
        if not ok or not 0.0 < float(self.speed) <= 100.0:
            raise ValueError(
                f"perturbation speed: must be a number in (0, 100], got {self.speed!r}"
            )

    @property
    def is_identity(self) -> bool:
        return self.delay == 0 and float(self.speed) == 1.0

    @property
    def label(self) -> str:
        parts = ([f"delay={self.delay}"] if self.delay else []) + (
            [f"speed={self.speed:g}"] if float(self.speed) != 1.0 else []
        )
        return ",".join(parts) or "none"

    @property
    def folder_suffix(self) -> str:
        """An evaluation folder's name ends in it: '' unperturbed, else e.g. '-delay3-speed1.3'."""
        return "" if self.is_identity else "-" + self.label.replace("=", "").replace(",", "-")


def parse_perturbation(text: str) -> Perturbation:
    """'delay=6', 'speed=1.3', 'delay=3,speed=0.7' (or 'none') -> Perturbation; ValueError naming
    the bad part."""
    text = text.strip()
    if text in ("", "none"):
        return Perturbation()
    fields: dict[str, int | float] = {}
    for part in text.split(","):
        m = re.fullmatch(r"\s*(delay|speed)\s*=\s*([^\s,]+)\s*", part)
        if not m:
            raise ValueError(f"--perturb {text!r}: expected delay=K and/or speed=S, e.g. delay=6")
        name, raw = m.groups()
        if name in fields:
            raise ValueError(f"--perturb {text!r}: {name} given twice")
        try:
            fields[name] = int(raw) if name == "delay" else float(raw)
        except ValueError:
            kind = "an int of steps" if name == "delay" else "a number"
            raise ValueError(f"--perturb {text!r}: {name} must be {kind}, got {raw!r}") from None
    return Perturbation(**fields)  # type: ignore[arg-type]


def _retime(pos: Array, mask: Array, delay: int, speed: float) -> tuple[Array, Array]:
    """pos [T + 1, H, 2], mask [T + 1, H] of one task -> the perturbed pair."""
    n = pos.shape[0]
    t = jnp.arange(n, dtype=jnp.float32)
    src = jnp.clip(speed * jnp.maximum(t - delay, 0.0), 0.0, n - 1)
    lo = jnp.floor(src).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, n - 1)
    w = (src - lo)[:, None, None]
    new_pos = (1.0 - w) * pos[lo] + w * pos[hi]
    exact = w[..., 0] < 1e-5  # on a step (up to float rounding of S t): its presence alone
    new_mask = jnp.where(exact, mask[lo], mask[lo] & mask[hi])
    return new_pos.astype(pos.dtype), new_mask


def perturb_tasks(tasks: TaskParams, p: Perturbation) -> TaskParams:
    """The task set with the people's timing perturbed (see the module docstring); stacked
    (leading task axis) or single tasks alike."""
    if p.is_identity:
        return tasks
    fn = lambda pos, mask: _retime(pos, mask, p.delay, float(p.speed))
    if tasks.human_pos.ndim == 4:
        fn = jax.vmap(fn)
    pos, mask = fn(tasks.human_pos, tasks.human_mask)
    return tasks.replace(human_pos=pos, human_mask=mask)


def delay_people(tasks: TaskParams, delays: Array) -> TaskParams:
    """Every person h holds its step-0 position (and presence) `delays[..., h]` more steps, then
    follows its path: new[t, h] = old[max(t - d_h, 0), h]. `delays` is [H] for a single task or
    [N, H] for a stacked task set (non-negative ints). The training-side counterpart of the
    evaluation's `delay=K` (which is this with every d_h = K), used by the extension
    `TrainConfig.crowd_delay_max`; pure JAX, jit- and vmap-friendly."""

    def one(pos: Array, mask: Array, d: Array) -> tuple[Array, Array]:
        t = jnp.arange(pos.shape[0])[:, None]
        src = jnp.clip(t - d[None, :], 0, pos.shape[0] - 1)  # [T + 1, H]
        new_pos = jnp.take_along_axis(pos, src[..., None], axis=0)
        return new_pos, jnp.take_along_axis(mask, src, axis=0)

    delays = jnp.asarray(delays, jnp.int32)
    fn = jax.vmap(one) if tasks.human_pos.ndim == 4 else one
    pos, mask = fn(tasks.human_pos, tasks.human_mask, delays)
    return tasks.replace(human_pos=pos, human_mask=mask)
