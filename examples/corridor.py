"""A task family of your own: a robot crossing a corridor against people walking the other way.

Copy this file to start your own family; docs/custom_tasks.md walks through it. Importing the
module registers the family "corridor" with `mpcpearl_jax.envs.register`, after which every part
of the project (trainer, MPC, evaluation, metrics, figures) works on it unchanged:

    python -m experiments.restaurant --env examples.corridor:corridor --preset smoke
    python -m examples.corridor                  # the same from Python (`train` below)

A task is a `TaskParams` (one task; T = horizon, H = people, S = static obstacles): the people's
positions at every step [T + 1, H, 2] and their presence [T + 1, H], the static obstacles as
rounded boxes (lower and upper corners [S, 2], rounding radius [S]; a round pillar is a box with
lo == hi), the start pose (x, y, heading) [3] and the goal (x, y) [2]. What is fixed for the
whole family (time step, horizon, speed limit, arena, observation options) is its `NavConfig`.
Every task of a family must have the same H and S (absent people are masked, not removed).
"""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from mpcpearl_jax.envs import NavConfig, TaskParams, register
from mpcpearl_jax.envs.types import stack_params

NAME = "corridor"
LENGTH, WIDTH = 10.0, 4.0  # metres: the arena is the corridor's floor (its walls clip the robot)
NUM_PEOPLE = 3
NUM_PILLARS = 2
PILLAR_RADIUS = 0.3
SPLIT_SIZES = {"train": 40, "val": 8, "test": 8, "ood": 8}
SPEEDS = {"ood": (1.6, 2.4)}  # people's walking speeds (m/s); OOD tasks: faster than in training
TRAIN_SPEEDS = (0.8, 1.6)

CONFIG = NavConfig(
    name=NAME,
    dt=0.05,
    horizon=80,  # 4 s per episode
    v_max=4.0,
    arena_lo=(-LENGTH / 2, -WIDTH / 2),
    arena_hi=(LENGTH / 2, WIDTH / 2),
    observe_static=True,  # the pillars' centres are part of the observation
)


def layout(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """What stays when a task's people are drawn again: pillars, start pose and goal."""
    lane = WIDTH / 2 - 0.6
    pillars = np.stack(
        [rng.uniform(-2.5, 2.5, NUM_PILLARS), rng.uniform(-lane, lane, NUM_PILLARS)], axis=-1
    )
    return {
        "pillars": pillars,
        "start": np.array([-LENGTH / 2 + 0.8, rng.uniform(-lane, lane), 0.0]),
        "goal": np.array([LENGTH / 2 - 0.8, rng.uniform(-lane, lane)]),
    }


def people(
    rng: np.random.Generator, config: NavConfig, speeds: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Positions [T + 1, H, 2] and presence [T + 1, H]: each person enters at the far end at its
    own step, walks towards the robot's end along its own lane at its own speed, and leaves."""
    steps = np.arange(config.horizon + 1)[:, None]
    lane = rng.uniform(-WIDTH / 2 + 0.4, WIDTH / 2 - 0.4, NUM_PEOPLE)
    speed = rng.uniform(*speeds, NUM_PEOPLE)
    enter = rng.integers(0, config.horizon // 2, NUM_PEOPLE)
    x = LENGTH / 2 - speed * np.maximum(steps - enter, 0) * config.dt
    pos = np.stack([x, np.broadcast_to(lane, x.shape)], axis=-1)
    present = (steps >= enter) & (x > -LENGTH / 2)
    return pos, present


def task(where: dict[str, np.ndarray], pos: np.ndarray, present: np.ndarray) -> TaskParams:
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    return TaskParams(
        human_pos=f32(pos),
        human_mask=jnp.asarray(present, bool),
        static_lo=f32(where["pillars"]),
        static_hi=f32(where["pillars"]),
        static_radius=f32(np.full(NUM_PILLARS, PILLAR_RADIUS)),
        start=f32(where["start"]),
        goal=f32(where["goal"]),
    )


def _rng(*keys: int | str) -> np.random.Generator:
    ints = [zlib.crc32(k.encode()) if isinstance(k, str) else int(k) for k in keys]
    return np.random.default_rng(np.random.SeedSequence(ints))


def build(split: str, seed: int, config: NavConfig, **options: Any) -> TaskParams:
    """The builder `register` takes: the tasks of `split` for task-set `seed`, stacked on a
    leading axis. A split the family lacks is a ValueError (the trainer then validates on the
    first training tasks, and the final evaluation skips a missing 'ood')."""
    if options:
        raise TypeError(f"make_tasks({NAME!r}) got unexpected options {sorted(options)}")
    if split not in SPLIT_SIZES:
        raise ValueError(f"the {NAME} family has no {split!r} split; it has {list(SPLIT_SIZES)}")
    tasks = []
    for i in range(SPLIT_SIZES[split]):
        rng = _rng(seed, split, i)
        tasks.append(task(layout(rng), *people(rng, config, SPEEDS.get(split, TRAIN_SPEEDS))))
    return stack_params(tasks)


def redraw(
    seed: int, config: NavConfig, task_ids: Any, stream: tuple[int, ...], **options: Any
) -> TaskParams:
    """Optional: training tasks `task_ids` with their people drawn anew (pillars, start and goal
    kept) from the random stream `stream`; it lets `train.redraw_behaviours` (the `cpu-explore`
    preset) run on this family."""
    tasks = []
    for i in np.asarray(task_ids).reshape(-1):
        where = layout(_rng(seed, "train", int(i)))
        pos, present = people(_rng(seed, "redraw", *stream, int(i)), config, TRAIN_SPEEDS)
        tasks.append(task(where, pos, present))
    return stack_params(tasks)


# the MPC's speed cap: the env's own v_max (the restaurant's MPC keeps the authors' 5 m/s)
register(NAME, CONFIG, build, redraw=redraw, mpc_defaults={"v_max": None})


def train(
    out: str | Path, preset: str = "smoke", changes: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Train MPC-PEARL on the corridor from Python, then evaluate it as the command line does
    (results.json and figures in `out`); returns the results. `changes`: config fields by
    dotted name, e.g. {"train.iterations": 2, "train.eps": 0.2}."""
    import mpcpearl_jax
    from mpcpearl_jax.config import resolve

    cfg = resolve(preset, NAME, changes=changes)  # checked across fields
    _, results = mpcpearl_jax.train(cfg, out)
    return results


if __name__ == "__main__":
    results = train(Path("runs") / "corridor-smoke")
    print(f"test SR {results['test_adapt']['SR']:.2f}")
