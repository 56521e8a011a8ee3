"""The paper's own restaurant scenarios as a task source (the authors' published crowds).

The authors published the crowds their table was computed on: precomputed trajectories of six
people for 205 tasks (`scenarios/X.npy`) and 25 out-of-distribution tasks
(`scenarios_out_of_distribution/X.npy`), each of shape (task, x/y, step 0..80, person), in metres
at dt = 0.05 s. This module reads them from a folder with that layout (a clone of the authors'
repository, or any folder holding the same files) and builds `TaskParams` for the restaurant env;
the environment, reward, MPC and observation options are the project's, unchanged.

Splits (`scenario_ids`):
  train  the authors' training tasks 0..179 (180 tasks); with `hold_out_val` 0..149;
  val    tasks 150..179 of the authors' training tasks (30 tasks, six per table configuration),
         this project's fixed hold-out for choosing settings; train with `hold_out_val` when
         the choice is made on them;
  test   the authors' test tasks 180..204 (25 tasks);
  ood    the 25 out-of-distribution tasks, with the authors' shifted tables.

Task i uses table configuration i % 5 (the first five of `TABLE_CONFIGS`); OOD task j uses
configuration j % 5 with every table's x moved to the authors' drawn value (`OOD_TABLE_X`, y
unchanged). Start (-4.5, 4.5, -pi/8) and goal (3.5, -3.5) are the restaurant's.

Files are checked on load (missing file, shape, dtype, NaN/inf, people outside the arena); a bad
file raises one line naming it. `scenario_digests` gives the sha256 of each file, which runs
record in their config (`task_options["scenario_sha256"]`) and which is checked again whenever the
run's tasks are rebuilt.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from mpcpearl_jax.envs.restaurant.generator import (
    GRID,
    NUM_HUMANS,
    NUM_TABLES,
    TABLE_CONFIGS,
    TABLE_RADIUS,
)
from mpcpearl_jax.envs.types import NavConfig, TaskParams
from mpcpearl_jax.errors import DataFormatError

MAIN_FILE = "scenarios/X.npy"
OOD_FILE = "scenarios_out_of_distribution/X.npy"
NUM_SCENARIO_CONFIGS = 5  # task i uses table configuration i % 5
NUM_SCENARIO_TRAIN = 180  # the authors' split: 0..179 train, 180..204 test
NUM_SCENARIO_TASKS = 205
NUM_SCENARIO_OOD = 25
VAL_IDS = tuple(range(150, 180))  # this project's hold-out of the authors' training tasks
START = (-4.5, 4.5, -np.pi / 8)
GOAL = (3.5, -3.5)
# the x of every table of the OOD tasks (the authors' seed-2021 draw), per configuration, in the
# order of the configuration's grid indices; y stays the grid's
OOD_TABLE_X: tuple[tuple[float, ...], ...] = (
    (-3.303, 1.633, -0.569, 1.844, -0.999),
    (-3.064, -0.589, 1.624, -3.331, 1.608),
    (-0.548, -3.029, -0.981, 1.692, 1.957),
    (-0.781, 1.692, -3.482, -0.787, -0.686),
    (1.774, -3.101, -0.785, -3.098, -0.792),
)
SPLIT_FILE = {"train": MAIN_FILE, "val": MAIN_FILE, "test": MAIN_FILE, "ood": OOD_FILE}
SCENARIO_OPTIONS = frozenset({"scenarios", "hold_out_val", "scenario_sha256"})


def scenario_ids(split: str, hold_out_val: bool = False) -> list[int]:
    """Indices into the file of `split` (see the module docstring)."""
    if split == "train":
        n = VAL_IDS[0] if hold_out_val else NUM_SCENARIO_TRAIN
        return list(range(n))
    if split == "val":
        return list(VAL_IDS)
    if split == "test":
        return list(range(NUM_SCENARIO_TRAIN, NUM_SCENARIO_TASKS))
    if split == "ood":
        return list(range(NUM_SCENARIO_OOD))
    raise ValueError(f"unknown split {split!r} for the paper's scenarios")


def sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def scenario_digests(directory: str | Path) -> dict[str, str]:
    """sha256 of the scenario files present in `directory` (the OOD file is optional); raises
    FileNotFoundError naming the folder or the main file when they are missing."""
    root = Path(directory)
    if not root.is_dir():
        raise FileNotFoundError(f"scenarios folder {root}: no such directory")
    if not (root / MAIN_FILE).is_file():
        raise FileNotFoundError(
            f"{root / MAIN_FILE}: no such file (the scenarios folder must hold {MAIN_FILE}, "
            f"optionally {OOD_FILE}, as in the authors' repository)"
        )
    return {name: sha256(root / name) for name in (MAIN_FILE, OOD_FILE) if (root / name).is_file()}


def load_scenario_file(
    path: str | Path, num_tasks: int, cfg: NavConfig, expected_sha256: str | None = None
) -> np.ndarray:
    """Read and check one scenario file -> people's positions [N, T + 1, H, 2] float32.

    Raises FileNotFoundError (missing file) or DataFormatError (not a NumPy array, wrong shape or
    dtype, NaN/inf, a person outside the arena, or a sha256 other than the expected one), each one
    line naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if expected_sha256 is not None:
        digest = sha256(path)
        if digest != expected_sha256:
            raise DataFormatError(
                f"{path}: sha256 {digest[:12]}... differs from the run's record "
                f"{expected_sha256[:12]}... (not the file the run was trained on)"
            )
    try:
        x = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise DataFormatError(f"{path}: not a NumPy .npy array ({e})") from None
    want = (num_tasks, 2, cfg.horizon + 1, NUM_HUMANS)
    if not isinstance(x, np.ndarray) or x.shape != want:
        shape = getattr(x, "shape", None)
        raise DataFormatError(
            f"{path}: shape {shape}, expected {want} (task, x/y, step 0..{cfg.horizon}, person)"
        )
    if x.dtype.kind != "f":
        raise DataFormatError(f"{path}: dtype {x.dtype}, expected floating point positions")
    bad = ~np.isfinite(x)
    if bad.any():
        task = int(np.argwhere(bad)[0][0])
        raise DataFormatError(f"{path}: non-finite position (NaN or inf) in task {task}")
    lo = np.asarray(cfg.arena_lo, dtype=np.float64)[None, :, None, None]
    hi = np.asarray(cfg.arena_hi, dtype=np.float64)[None, :, None, None]
    outside = (x < lo - 1e-6) | (x > hi + 1e-6)
    if outside.any():
        task, axis, step, person = (int(v) for v in np.argwhere(outside)[0])
        raise DataFormatError(
            f"{path}: person {person} of task {task} is outside the arena at step {step} "
            f"({'xy'[axis]} = {x[task, axis, step, person]:.3f}, arena {cfg.arena_lo} to "
            f"{cfg.arena_hi})"
        )
    return np.transpose(x, (0, 2, 3, 1)).astype(np.float32)


def scenario_tables(split: str, index: int) -> np.ndarray:
    """Table centres [5, 2] of task `index` of the scenario file of `split`."""
    config = index % NUM_SCENARIO_CONFIGS
    centres = GRID[list(TABLE_CONFIGS[config])].copy()
    if split == "ood":
        centres[:, 0] = OOD_TABLE_X[config]
    return centres


def make_scenario_tasks(
    split: str,
    cfg: NavConfig,
    scenarios: str | Path,
    hold_out_val: bool = False,
    scenario_sha256: dict[str, str] | None = None,
) -> TaskParams:
    """Stacked tasks of a split of the scenarios in folder `scenarios` (module docstring).

    `scenario_sha256` (file name -> digest, as `scenario_digests` gives it) makes the load check
    that each file read is the one recorded."""
    if split not in SPLIT_FILE:
        raise ValueError(f"unknown split {split!r}; expected one of {tuple(SPLIT_FILE)}")
    if not isinstance(hold_out_val, bool):
        raise ValueError(f"hold_out_val: must be true or false, got {hold_out_val!r}")
    root = Path(scenarios)
    if not root.is_dir():
        raise FileNotFoundError(f"scenarios folder {root}: no such directory")
    name = SPLIT_FILE[split]
    expected = (scenario_sha256 or {}).get(name)
    n = NUM_SCENARIO_OOD if split == "ood" else NUM_SCENARIO_TASKS
    people = load_scenario_file(root / name, n, cfg, expected)
    ids = scenario_ids(split, hold_out_val)
    pos = jnp.asarray(people[np.asarray(ids)])  # [N, T + 1, H, 2]
    tables = jnp.asarray(np.stack([scenario_tables(split, i) for i in ids]))
    n_t = len(ids)
    return TaskParams(
        human_pos=pos,
        human_mask=jnp.ones(pos.shape[:3], dtype=bool),
        static_lo=tables,
        static_hi=tables,
        static_radius=jnp.full((n_t, NUM_TABLES), TABLE_RADIUS, jnp.float32),
        start=jnp.tile(jnp.asarray(START, jnp.float32), (n_t, 1)),
        goal=jnp.tile(jnp.asarray(GOAL, jnp.float32), (n_t, 1)),
    )


def scenario_options(directory: str | Path, hold_out_val: bool = False) -> dict[str, Any]:
    """The `task_options` that make a run's tasks the scenarios in `directory`: the folder, the
    hold-out choice and the sha256 of each file (recorded in the run's config.json). Every file
    present is read and checked here (FileNotFoundError / DataFormatError naming it)."""
    digests = scenario_digests(directory)
    # every file now, the OOD one included: a bad one is found before training, not at the
    # final evaluation (where a missing OOD split is skipped)
    from mpcpearl_jax.envs.restaurant import RESTAURANT_CONFIG

    for name, n in ((MAIN_FILE, NUM_SCENARIO_TASKS), (OOD_FILE, NUM_SCENARIO_OOD)):
        if name in digests:
            load_scenario_file(Path(directory) / name, n, RESTAURANT_CONFIG, digests[name])
    out: dict[str, Any] = {"scenarios": str(directory), "scenario_sha256": digests}
    if hold_out_val:
        out["hold_out_val"] = True
    return out


def uses_scenarios(task_options: dict) -> bool:
    return bool(task_options.get("scenarios"))


def check_val_split(task_options: dict, split: str) -> None:
    """A run trained on every training scenario has seen the val tasks: refuse to score it there."""
    if split == "val" and uses_scenarios(task_options) and not task_options.get("hold_out_val"):
        raise ValueError(
            f"the run trained on the scenario tasks {VAL_IDS[0]}-{VAL_IDS[-1]} that form the val "
            "split (train with --hold-out-val to choose settings on them)"
        )
