"""The policy's observation from plain arrays, shared by `NavEnv.observe` and `deploy.observe`.

Everything a navigation policy sees is described once, in `PARTS`: each part's name, whose
entries it holds (the robot's own, one per person or one per static obstacle), its width per
entity, the env option that turns it on and what its entries mean. The observation
(`observation`), its length (`obs_dim`), its documented layout (`layout`, also the exported
policy's sidecar), the crowd encoder's entity groups (`group`), the options an exported policy
records (`OPTIONS`) and config validation (`missing_options`) all derive from it. The env reads
its arrays from `TaskParams` and `EnvState`, a robot's control loop from its sensors
(`mpcpearl_jax.deploy.adapter`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable

import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs.types import NavConfig

ENTITIES = ("robot", "people", "static")


@dataclasses.dataclass(frozen=True)
class Part:
    """One part of the observation.

    `entity`: whose entries it holds: "robot" (once), "people" (one block per person, persons in
    order) or "static" (one block per static obstacle). `width`: entries per entity. `option`:
    the NavConfig field that turns it on (None: always there); an integer option (the
    forecast's number of points) also repeats the width that many times. `scales`: the NavConfig
    fields its values are scaled by. `meaning`: its entries in words, under a config.
    """

    name: str
    entity: str
    width: int
    option: str | None
    meaning: Callable[[NavConfig], str]
    scales: tuple[str, ...] = ()

    def on(self, config: NavConfig) -> bool:
        return self.option is None or bool(getattr(config, self.option))

    def size(self, config: NavConfig, num_people: int, num_static: int) -> int:
        """Entries of this part (0 when its option is off)."""
        if not self.on(config):
            return 0
        count = {"robot": 1, "people": num_people, "static": num_static}[self.entity]
        repeat = 1 if self.option is None else int(getattr(config, self.option))
        return self.width * repeat * count


def _ego(config: NavConfig) -> str:
    return f"/ {config.relative_scale:g} m, clipped to [-1, 1]"


def _forecast(config: NavConfig) -> str:
    k, st = config.observe_forecast, config.forecast_stride
    what = f"each person's position {st}, ..., {k * st} steps ahead at constant velocity"
    return f"{what}, [H, {k}, 2] in the robot frame {_ego(config)}"


# the observation's parts, in order
PARTS = (
    Part("robot_xy", "robot", 2, None, lambda c: "robot position, arena mapped to [-1, 1]"),
    Part("robot_heading", "robot", 1, None, lambda c: "heading / pi"),
    Part(
        "people_xy",
        "people",
        2,
        None,
        lambda c: "people positions, arena mapped to [-1, 1]; absent (-1, -1)",
    ),
    Part(
        "people_velocity",
        "people",
        2,
        "observe_velocity",
        lambda c: (
            f"people's last-step displacement / ({c.velocity_scale:g} m/s * dt), clipped"
            "; 0 if absent now or a step ago"
        ),
        ("velocity_scale",),
    ),
    Part(
        "static_centres",
        "static",
        2,
        "observe_static",
        lambda c: "static obstacle centres, mapped to [-1, 1]",
    ),
    Part(
        "people_ego",
        "people",
        2,
        "observe_relative",
        lambda c: f"people in the robot frame {_ego(c)}; absent (1, 1)",
        ("relative_scale",),
    ),
    Part(
        "static_ego",
        "static",
        2,
        "observe_relative",
        lambda c: f"nearest static points in the robot frame {_ego(c)}",
        ("relative_scale",),
    ),
    Part(
        "goal_ego",
        "robot",
        2,
        "observe_relative",
        lambda c: f"goal in the robot frame {_ego(c)}",
        ("relative_scale",),
    ),
    Part(
        "people_forecast",
        "people",
        2,
        "observe_forecast",
        _forecast,
        ("relative_scale", "forecast_stride"),
    ),
    Part(
        "people_present",
        "people",
        1,
        "observe_presence",
        lambda c: "1 if the person is present (and in range), else -1",
    ),
    Part(
        "time", "robot", 1, "observe_time", lambda c: "2 t / T - 1, T the episode length in steps"
    ),
)
PART = {p.name: p for p in PARTS}
# options that change every part rather than turn one on: a range beyond which a person looks
# absent, and the people listed nearest first
MODIFIERS = ("sensing_radius", "observe_sorted")
# every NavConfig option that shapes the observation (in NavConfig's order), as an exported
# policy records them
OPTIONS = tuple(
    f.name
    for f in dataclasses.fields(NavConfig)
    if f.name in {p.option for p in PARTS} | {s for p in PARTS for s in p.scales} | set(MODIFIERS)
)


def parts(config: NavConfig) -> tuple[Part, ...]:
    """The parts `config`'s options turn on, in order."""
    return tuple(p for p in PARTS if p.on(config))


def group(entity: str) -> tuple[str, ...]:
    """The names of the parts of one entity ("robot", "people" or "static"), in order: the
    entries an entity-wise reader (`pearl.networks.CrowdEncoder`) joins into one entity."""
    return tuple(p.name for p in PARTS if p.entity == entity)


def missing_options(present: Iterable[str], needed: Iterable[str]) -> list[str]:
    """The options that turn on the parts `needed` not among the part names `present`."""
    have = set(present)
    out: list[str] = []
    for name in needed:
        option = PART[name].option
        if name not in have and option is not None and option not in out:
            out.append(option)
    return out


def obs_dim(config: NavConfig, num_people: int, num_static: int) -> int:
    """Length of the observation of a family with `num_people` people and `num_static` static
    obstacles under `config`'s observation options."""
    return sum(p.size(config, num_people, num_static) for p in parts(config))


def normalize_xy(config: NavConfig, p: Array) -> Array:
    """Arena coordinates [..., 2] mapped to [-1, 1] (clipped)."""
    lo = jnp.asarray(config.arena_lo)
    hi = jnp.asarray(config.arena_hi)
    return jnp.clip(2.0 * (p - lo) / (hi - lo) - 1.0, -1.0, 1.0)


def observation(
    config: NavConfig,
    pose: Array,
    t: Array,
    humans: Array,
    mask: Array,
    prev: Array,
    prev_mask: Array,
    static_lo: Array,
    static_hi: Array,
    goal: Array,
) -> Array:
    """Observation [O] in [-1, 1] (`obs_dim`), the parts of `PARTS` that `config` turns on,
    concatenated in order.

    Args:
      pose: [3] robot (x, y, heading); t: [] steps since the episode began.
      humans, mask: [H, 2] people positions and [H] presence at step t.
      prev, prev_mask: the same people at step t - 1 (at t = 0: those of step 0).
      static_lo, static_hi: [S, 2] static obstacles as boxes; goal: [2].

    Parts, in order (`layout` gives their offsets and sizes):
      robot_xy [2], robot_heading [1]: the pose;
      people_xy [H, 2]: the people (absent ones at (-1, -1));
      people_velocity [H, 2]: their last-step displacement (option `observe_velocity`);
      static_centres [S, 2]: the static obstacles' centres (option `observe_static`);
      people_ego [H, 2], static_ego [S, 2], goal_ego [2]: the people, the nearest static points
        and the goal in the robot's frame (option `observe_relative`);
      people_forecast [H, K, 2]: each person's position K points ahead at constant velocity, in
        the robot's frame (option `observe_forecast` = K, with `observe_relative`);
      people_present [H]: 1 present, -1 absent (option `observe_presence`);
      time [1]: the elapsed time 2 t / T - 1 (option `observe_time`).
    With `sensing_radius` a person farther than it from the robot counts as absent throughout;
    with `observe_sorted` the people are listed nearest first in every part.
    """
    dist = jnp.linalg.norm(humans - pose[:2], axis=-1)
    if config.sensing_radius > 0:  # extension: people out of range look absent
        mask = mask & (dist <= config.sensing_radius)
    if config.observe_sorted:  # extension: nearest person first
        order = jnp.argsort(jnp.where(mask, dist, jnp.inf), stable=True)
        humans, mask, prev, prev_mask = (x[order] for x in (humans, mask, prev, prev_mask))
    on = parts(config)
    names = {p.name for p in on}
    h = jnp.where(mask[:, None], normalize_xy(config, humans), -1.0)
    value = {
        "robot_xy": normalize_xy(config, pose[:2]),
        "robot_heading": pose[2:3] / jnp.pi,
        "people_xy": h.reshape(-1),
    }
    if "people_velocity" in names:  # extension: people's last-step displacement
        scale = config.velocity_scale * config.dt
        vel = jnp.clip((humans - prev) / scale, -1.0, 1.0)
        value["people_velocity"] = jnp.where((mask & prev_mask)[:, None], vel, 0.0).reshape(-1)
    if "static_centres" in names:
        value["static_centres"] = normalize_xy(config, 0.5 * (static_lo + static_hi)).reshape(-1)
    if "people_ego" in names:  # extension: egocentric positions
        pos, th = pose[:2], pose[2]
        c, s = jnp.cos(th), jnp.sin(th)

        def ego(q: Array) -> Array:  # world points [N, 2] -> robot frame, scaled, clipped
            d = q - pos
            local = jnp.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
            return jnp.clip(local / config.relative_scale, -1.0, 1.0)

        nearest = jnp.clip(pos, static_lo, static_hi)  # [S, 2]
        value["people_ego"] = jnp.where(mask[:, None], ego(humans), 1.0).reshape(-1)
        value["static_ego"] = ego(nearest).reshape(-1)
        value["goal_ego"] = ego(goal[None]).reshape(-1)
        if "people_forecast" in names:  # extension: constant-velocity foresight
            step = jnp.where((mask & prev_mask)[:, None], humans - prev, 0.0)  # [H, 2]
            k = config.forecast_stride * jnp.arange(1, config.observe_forecast + 1)
            ahead = humans[:, None, :] + k[None, :, None] * step[:, None, :]  # [H, K, 2]
            fut = jnp.stack([ego(ahead[:, i]) for i in range(config.observe_forecast)], 1)
            value["people_forecast"] = jnp.where(mask[:, None, None], fut, 1.0).reshape(-1)
    if "people_present" in names:  # extension: who is there, for a crowd encoder's mask
        value["people_present"] = jnp.where(mask, 1.0, -1.0)
    if "time" in names:  # extension: elapsed fraction of the episode
        value["time"] = (2.0 * t / config.horizon - 1.0).reshape(1)
    return jnp.concatenate([value[p.name] for p in on]).astype(jnp.float32)


def layout(config: NavConfig, num_people: int, num_static: int) -> list[dict]:
    """The parts of the observation as [{name, start, size, meaning}] (for documentation and the
    sidecar of an exported policy)."""
    out, start = [], 0
    for p in parts(config):
        size = p.size(config, num_people, num_static)
        out.append({"name": p.name, "start": start, "size": size, "meaning": p.meaning(config)})
        start += size
    return out
