"""Many devices and hosts on JAX's own runtime: the seed mesh, `jax.distributed` start-up, and host
reads of sharded arrays.

Training shards the leading seed axis of `TrainState` (and the flat seeds x tasks x episodes
collection batch, whose rows are grouped by seed) over a one-axis `jax.sharding.Mesh` named
`seeds`. Every seed's computation is the same program as on one device (the same keys), so the
per-seed results do not depend on how the seeds are laid out. With one device no mesh is built
and nothing changes. docs/distributed.md describes the layout, the MPC callback and the commands.

Several processes (hosts): each one calls `initialize` first (before any JAX computation), then
runs the same program; each holds the seeds of its own devices, reads of whole arrays go through
`to_host` (a collective every process takes part in), and files outside orbax's checkpoints are
written by process 0 only (`is_primary`).
"""

from __future__ import annotations

import socket
import threading
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from mpcpearl_jax.errors import ConfigError

AXIS = "seeds"  # the mesh axis: seeds (and each seed's collection rows) are split along it
JOIN_TIMEOUT_S = 120.0  # default wait for the coordinator and the other processes
NOTICE_S = 5.0  # a start-up slower than this says what it waits for


class CoordinatorTimeout(ConfigError):
    """The distributed runtime did not start within the time given. Its start-up is still
    blocked in a thread of the runtime (which would abort the process later): after reporting
    this error, end the process at once with `os._exit`."""


def initialize(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    timeout_s: float = JOIN_TIMEOUT_S,
) -> bool:
    """Start JAX's distributed runtime (`jax.distributed.initialize`) when the three options are
    given (all or none; False when none). On CPU the collectives use gloo, so several processes
    on one machine (or hosts without accelerators) train one sharded program. Must run before
    any JAX computation; ConfigError naming the option otherwise.

    The runtime aborts the whole process (a C++ stack, exit 134) when the coordinator does not
    answer or a process does not join in time; so it starts in a thread with a longer deadline of
    its own, and when `timeout_s` seconds pass first, CoordinatorTimeout names the coordinator."""
    given = (coordinator, num_processes, process_id)
    if all(v is None for v in given):
        return False
    if any(v is None for v in given):
        raise ConfigError(
            "--coordinator, --num-processes and --process-id go together (give all three)"
        )
    assert coordinator is not None and num_processes is not None and process_id is not None
    host, sep, port = str(coordinator).rpartition(":")
    if not (sep and host and port.isdigit() and 0 < int(port) < 65536):
        raise ConfigError(f"--coordinator {coordinator!r}: expected HOST:PORT (e.g. 10.0.0.1:1234)")
    if not (isinstance(num_processes, int) and num_processes >= 1):
        raise ConfigError(f"--num-processes: must be a positive int, got {num_processes!r}")
    if not (isinstance(process_id, int) and 0 <= process_id < num_processes):
        raise ConfigError(
            f"--process-id: must lie in [0, {num_processes - 1}] (--num-processes "
            f"{num_processes}), got {process_id!r}"
        )
    if not (isinstance(timeout_s, (int, float)) and 0 < timeout_s < float("inf")):
        raise ConfigError(f"--coordinator-timeout: must be a positive number, got {timeout_s!r}")
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise ConfigError(
            "--coordinator: JAX already started a backend in this process; "
            "jax.distributed.initialize must come first"
        )
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    errors: list[BaseException] = []

    def start() -> None:
        try:  # the runtime's own deadline comes well after ours
            jax.distributed.initialize(
                coordinator,
                num_processes,
                process_id,
                initialization_timeout=int(timeout_s) + 60,
            )
        except Exception as e:  # noqa: BLE001 - reported by the caller's thread
            errors.append(e)

    thread = threading.Thread(target=start, name="jax-distributed-start", daemon=True)
    thread.start()
    thread.join(min(NOTICE_S, timeout_s))
    if thread.is_alive():  # say what it waits for rather than nothing
        from mpcpearl_jax.notices import warn

        warn(
            f"waiting for the coordinator at {coordinator} and the other processes (at most "
            f"{timeout_s:g} s, --coordinator-timeout)"
        )
        thread.join(max(timeout_s - NOTICE_S, 0.0))
    if thread.is_alive():
        raise CoordinatorTimeout(_no_answer(coordinator, host, int(port), process_id, timeout_s))
    if errors:
        e = errors[0]
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ConfigError(f"--coordinator {coordinator}: cannot join ({first})") from e
    return True


def _no_answer(coordinator: str, host: str, port: int, process_id: int, timeout_s: float) -> str:
    """The one line of a start-up that timed out: whether anything listens at the address."""
    waited = f"within {timeout_s:g} s (--coordinator-timeout)"
    if process_id == 0:
        return (
            f"--coordinator {coordinator}: not every process joined {waited}; start the same "
            "command with each --process-id"
        )
    try:
        with socket.create_connection((host, port), timeout=2.0):
            listening = "it accepts connections but the runtime did not start"
    except OSError as e:
        listening = f"nothing answers there ({e.strerror or type(e).__name__})"
    return (
        f"--coordinator {coordinator}: no answer {waited}: {listening}; is process 0 running "
        "with this address?"
    )


def select_devices(seeds: int, devices: int = 0) -> list:
    """The devices the seeds are split over: `devices` of them (0 = as many as divide the seeds
    evenly, at most every device), the same number from each process. ConfigError naming the
    field when the count is not available or does not split evenly."""
    procs = jax.process_count()
    per_proc = [
        sorted((d for d in jax.devices() if d.process_index == p), key=lambda d: d.id)
        for p in range(procs)
    ]
    local = min(len(ds) for ds in per_proc)
    total = procs * local
    where = f"{procs} processes x {local}" if procs > 1 else "this process"
    if devices:
        if devices > total:
            raise ConfigError(
                f"ExperimentConfig.devices: {devices} asked, {total} available ({where}); "
                "choose fewer (--devices)"
            )
        if devices % procs:
            raise ConfigError(
                f"ExperimentConfig.devices: {devices} devices do not split evenly over "
                f"{procs} processes; give a multiple of {procs}"
            )
        if seeds % devices:
            raise ConfigError(
                f"ExperimentConfig.seeds: {seeds} seed(s) do not split evenly over {devices} "
                "devices; give a multiple of --devices as --seeds"
            )
        n = devices
    else:
        fits = [procs * k for k in range(local, 0, -1) if seeds % (procs * k) == 0]
        if not fits:
            raise ConfigError(
                f"ExperimentConfig.seeds: {seeds} seed(s) do not split evenly over {procs} "
                f"processes; give a multiple of {procs} as --seeds"
            )
        n = fits[0]
    per = n // procs
    return [d for ds in per_proc for d in ds[:per]]


def make_mesh(seeds: int, devices: int = 0) -> Mesh | None:
    """The one-axis seed mesh over `select_devices(seeds, devices)`; None for one device (the
    single-device program, unchanged)."""
    chosen = select_devices(seeds, devices)
    if len(chosen) == 1 and jax.process_count() == 1:
        return None
    return Mesh(np.array(chosen), (AXIS,))


def seed_sharding(mesh: Mesh) -> NamedSharding:
    """Leading axis split over the mesh, the rest of each array whole on its device."""
    return NamedSharding(mesh, P(AXIS))


def constrain(tree: Any, mesh: Mesh | None) -> Any:
    """Inside jit: every leaf of `tree` (leading seed axis) laid out by `seed_sharding`; the
    identity without a mesh."""
    if mesh is None:
        return tree
    sharding = seed_sharding(mesh)
    return jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, sharding), tree)


def to_host(tree: Any) -> Any:
    """`jax.device_get`, also for arrays spread over several processes (gathered with a
    collective: every process must call it at the same point)."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    from jax.experimental import multihost_utils

    def leaf(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return jax.device_get(x)

    return jax.tree_util.tree_map(leaf, tree)


def first_local(x: Any) -> np.ndarray:
    """The first element of x read from this process's own shard (no collective): for values that
    are the same for every seed, such as the iteration count."""
    if isinstance(x, jax.Array):
        return np.asarray(x.addressable_shards[0].data).reshape(-1)[0]
    return np.asarray(x).reshape(-1)[0]


def is_primary() -> bool:
    """Whether this process writes the run's files (process 0; orbax coordinates checkpoints)."""
    return jax.process_index() == 0


def sum_over_processes(values: list[float]) -> list[float]:
    """Host numbers summed over processes (e.g. MPC counters); the values as given in one
    process."""
    if jax.process_count() == 1:
        return values
    from jax.experimental import multihost_utils

    arr = np.asarray(values, np.float64)  # (gathered as float32 unless x64 is on)
    return [float(x) for x in np.sum(multihost_utils.process_allgather(arr), axis=0)]
