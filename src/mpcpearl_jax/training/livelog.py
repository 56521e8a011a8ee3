"""Live training logs for TensorBoard, mirroring metrics.jsonl (optional; off by default).

`TensorBoardLog(run_dir / "tensorboard")` writes every numeric field of each metrics row as a
scalar under the same name (nested dicts such as `mpc_reasons` as `mpc_reasons/<key>`), with the
iteration as the step, and flushes after each row so that a long run can be watched with
`tensorboard --logdir runs/` (the `tensorboard` viewer is a separate `pip install tensorboard`).
The writer is `tensorboardX` (the optional extra `tensorboard`: `pip install -e ".[tensorboard]"`),
imported only when a log is opened.
`read_scalars(logdir)` reads the event files back without TensorBoard.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

TB_DIR = "tensorboard"


class LiveLogError(RuntimeError):
    """The TensorBoard writer is not available."""


def missing() -> str | None:
    """None if the TensorBoard writer can be used, else a one-line reason."""
    try:
        import tensorboardX  # noqa: F401
    except ImportError as e:
        return (
            "--tensorboard needs the tensorboardX package, an optional extra: pip install -e "
            f'".[tensorboard]" (or pip install tensorboardX) ({e})'
        )
    return None


def scalars_of(row: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """The numeric fields of a metrics row, flattened (`a/b` for nested dicts); no booleans,
    strings or non-finite values."""
    out: dict[str, float] = {}
    for key, value in row.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(scalars_of(value, f"{name}/"))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            if math.isfinite(value):
                out[name] = float(value)
    return out


class TensorBoardLog:
    """One TensorBoard run (an event file in `logdir`); `write(row)` logs one metrics row.

    purge_step: on a resumed run, the first iteration logged again (TensorBoard then hides the
    earlier file's points from that step on).
    """

    def __init__(self, logdir: str | Path, purge_step: int | None = None):
        reason = missing()
        if reason is not None:
            raise LiveLogError(reason)
        from tensorboardX import SummaryWriter

        self.logdir = Path(logdir)
        self._writer = SummaryWriter(str(self.logdir), purge_step=purge_step, flush_secs=10)

    def write(self, row: Mapping[str, Any], step: int | None = None) -> None:
        step = int(row["iteration"]) if step is None else step
        for name, value in scalars_of(row).items():
            if name != "iteration":
                self._writer.add_scalar(name, value, step)
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> TensorBoardLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _records(path: Path) -> Iterator[bytes]:
    """The records of a TFRecord file (length, crc, data, crc; checksums not verified)."""
    data = path.read_bytes()
    i = 0
    while i + 12 <= len(data):
        (n,) = struct.unpack("<Q", data[i : i + 8])
        start = i + 12
        if start + n + 4 > len(data):  # a record still being written
            break
        yield data[start : start + n]
        i = start + n + 4


def read_scalars(logdir: str | Path) -> dict[str, list[tuple[int, float]]]:
    """tag -> [(step, value), ...] from every event file under `logdir` (in file order)."""
    from tensorboardX.proto import event_pb2

    out: dict[str, list[tuple[int, float]]] = {}
    for path in sorted(Path(logdir).rglob("events.out.tfevents.*")):
        for rec in _records(path):
            event = event_pb2.Event.FromString(rec)
            for v in event.summary.value:
                if v.HasField("simple_value"):
                    out.setdefault(v.tag, []).append((int(event.step), float(v.simple_value)))
    return out
