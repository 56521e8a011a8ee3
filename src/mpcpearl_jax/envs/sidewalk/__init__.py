"""The sidewalk task family (method §4): a robot crossing a sidewalk among pedestrians.

People come from an ETH/UCY trajectory file (`make_tasks("sidewalk", split, data=PATH)`, e.g. UCY
Zara 01) or, by default, from a synthetic crowd with the same geometry.
"""

from typing import Any

from mpcpearl_jax.envs import register
from mpcpearl_jax.envs.sidewalk.loader import (
    DataFormatError,
    Scene,
    full_window_starts,
    interpolate_track,
    load_eth_ucy,
    select_longest,
    window_starts,
    window_tracks,
)
from mpcpearl_jax.envs.sidewalk.plot import plot_sidewalk
from mpcpearl_jax.envs.sidewalk.synthetic import SyntheticCrowd
from mpcpearl_jax.envs.sidewalk.tasks import (
    GOAL,
    NUM_HUMANS,
    START,
    make_sidewalk_tasks,
    sidewalk_boxes,
    split_indices,
    task_windows,
)
from mpcpearl_jax.envs.types import NavConfig, TaskParams

SIDEWALK_CONFIG = NavConfig(
    name="sidewalk",
    dt=0.04,
    horizon=250,
    v_max=1.8,  # paper; the authors' code uses 2.0
    arena_lo=(-0.021, -0.239),
    arena_hi=(15.132, 12.386),
    observe_static=False,  # observation: pose + 5 pedestrians (13-d)
)


def _builder(split: str, seed: int, config: NavConfig, **kwargs: Any) -> TaskParams:
    if split == "val":  # 25 train / 6 test windows leave none to hold out
        raise ValueError("the sidewalk family has no 'val' split (its windows are train or test)")
    return make_sidewalk_tasks(split, seed, config, **kwargs)


def _viewer(path, task: TaskParams, robots, config: NavConfig, title: str | None = None):
    """The paper's sidewalk style: pedestrians as circles, buildings as grey boxes."""
    plot_sidewalk(task, config, robots, path, title=title)
    return path


# the authors' MPC speed cap of 5 m/s is a restaurant setting: on the sidewalk the MPC may use
# the env's v_max
register(
    "sidewalk",
    SIDEWALK_CONFIG,
    _builder,
    viewer=_viewer,
    mpc_defaults={"v_max": None},
    online_eval=True,  # online adaptation is the sidewalk's headline evaluation, as in the paper
)

__all__ = [
    "GOAL",
    "NUM_HUMANS",
    "SIDEWALK_CONFIG",
    "START",
    "DataFormatError",
    "Scene",
    "SyntheticCrowd",
    "full_window_starts",
    "interpolate_track",
    "load_eth_ucy",
    "make_sidewalk_tasks",
    "plot_sidewalk",
    "select_longest",
    "sidewalk_boxes",
    "split_indices",
    "task_windows",
    "window_starts",
    "window_tracks",
]
