"""Export a trained policy as a portable artifact (see docs/deploy.md).

    python -m experiments.export RUN_DIR                     # RUN_DIR/policy.export (+ .json)
    python -m experiments.export RUN_DIR --out policy.export --seed-index 1

Writes the policy's `act` and the encoder's `infer_z`, serialized with `jax.export`, and a JSON
sidecar; `mpcpearl_jax.load_exported` (one file: `mpcpearl_jax/deploy/exported.py`, jax only) runs
them
without flax or the project's networks. A bad folder or seed index is a one-line error (exit 2);
a stop signal (Ctrl-C, SIGTERM, SIGHUP) one line and exit code 128 + the signal.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from experiments.common import one_line_errors, stops_with
from mpcpearl_jax.cli.platform import check_platform


def make_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.export",
        description="Export a run's policy (act, infer_z) with jax.export, plus a JSON sidecar.",
    )
    p.add_argument("run", type=Path, help="run directory (config.json + policy.msgpack)")
    p.add_argument(
        "--out",
        help="export file, or a folder for policy.export (default RUN_DIR/policy.export)",
    )
    p.add_argument("--seed-index", type=int, default=0, help="which seed of the run (default 0)")
    p.add_argument(
        "--platforms",
        default="cpu,cuda",
        help="comma-separated jax.export platforms the artifact runs on (default cpu,cuda)",
    )
    return p


@stops_with("interrupted before the export was complete; the same command writes it again")
def main(argv: list[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    import jax

    from mpcpearl_jax.deploy.export import export_policy, runs_here
    from mpcpearl_jax.deploy.exported import (
        check_format,
        check_sidecar,
        load_exported,
        sidecar_path,
    )

    if not args.run.is_dir():
        print(f"error: {args.run}: no such directory", file=sys.stderr)
        return 2
    platforms = tuple(p.strip() for p in args.platforms.split(",") if p.strip())
    # a run that does not load, or writing the export or its sidecar (a full disk, permissions)
    with one_line_errors(interrupted=None) as failed:
        check_platform()  # JAX_PLATFORMS naming a platform this machine lacks: one line
        out = export_policy(args.run, args.out, args.seed_index, platforms)
        if runs_here(platforms):
            meta = load_exported(out).meta  # read back: the files are usable as written
        else:  # not loadable on this machine: check the sidecar's format and fields only
            meta = json.loads(sidecar_path(out).read_text())
            check_format(meta, sidecar_path(out))
            check_sidecar(meta, sidecar_path(out))
    if failed.code is not None:
        return failed.code
    size = out.stat().st_size / 1024
    print(
        f"[export] {meta['label']} ({args.run.name}, seed {args.seed_index}): {out} "
        f"({size:.0f} KB) and {sidecar_path(out).name}; obs {meta['observation']['dim']}, latent "
        f"{meta['latent_dim']}, platforms {', '.join(platforms)}"
    )
    if not runs_here(platforms):
        print(
            f"[export] not for this machine's {jax.default_backend()}: load it where "
            f"{', '.join(platforms)} is the backend",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
