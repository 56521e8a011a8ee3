"""Compare finished (or checkpointed) runs: learning curves side by side and one results table.

    python -m lab.compare RUN_DIR [RUN_DIR ...] --out results/restaurant-cpu \
        [--gp-mpc runs/gp_mpc/restaurant_test.json]

Reads each run's metrics.jsonl and results.json (written by experiments.restaurant,
sidewalk or grbal) and
writes curves.png (train return, test return, SR, CFR against iteration and gradient steps), a
table.md with this project's numbers next to the paper's, and summary.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from mpcpearl_jax.evaluation.metrics import METRIC_NAMES
from mpcpearl_jax.evaluation.report import comparison_table, plot_learning_curves, run_label


class NotARun(ValueError):
    """A folder that is not a run directory, or one with an unreadable file."""


def _json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise NotARun(f"{path}: not valid JSON ({e})") from e


def _load(run: Path) -> tuple[dict, list[dict], dict | None]:
    from mpcpearl_jax.errors import CheckpointError
    from mpcpearl_jax.runfolder import LOG_FILE, read_log

    if not run.is_dir():
        raise NotARun(f"{run}: no such run directory")
    for name in ("config.json", LOG_FILE):
        if not (run / name).is_file():
            raise NotARun(f"{run}: not a run directory (no {name})")
    cfg = _json(run / "config.json")
    if not isinstance(cfg, dict):
        raise NotARun(f"{run / 'config.json'}: not a run configuration")
    try:
        rows = read_log(run / LOG_FILE)
    except CheckpointError as e:
        raise NotARun(str(e)) from e
    res_path = run / "results.json"
    res = _json(res_path) if res_path.is_file() else None
    return cfg, rows, res


def _gp_mpc_metrics(path: Path) -> dict:
    """The metrics of a record written by experiments.gp_mpc; NotARun naming the file."""
    if not path.is_file():
        raise NotARun(f"--gp-mpc {path}: no such file (a JSON written by experiments.gp_mpc)")
    try:
        record = _json(path)
    except NotARun as e:
        raise NotARun(f"--gp-mpc {e}") from None
    m = record.get("metrics", record) if isinstance(record, dict) else None
    if not isinstance(m, dict) or not any(isinstance(m.get(k), (int, float)) for k in METRIC_NAMES):
        raise NotARun(
            f"--gp-mpc {path}: not a record of experiments.gp_mpc (no metrics "
            f"{', '.join(METRIC_NAMES)})"
        )
    return m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lab.compare", description=__doc__)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--gp-mpc", type=Path, help="JSON written by experiments.gp_mpc")
    ap.add_argument(
        "--labels",
        help="comma-separated names of the runs in the figure and tables (default: each run's "
        "method label)",
    )
    ap.add_argument("--debug", action="store_true", help="show the traceback of an error")
    args = ap.parse_args(argv)
    try:
        loaded = [(r, *_load(r)) for r in args.runs]
        gp = _gp_mpc_metrics(args.gp_mpc) if args.gp_mpc else None
        names = [run_label(c) for _, c, _, _ in loaded]
        if args.labels is not None:
            names = [x.strip() for x in args.labels.split(",")]
            if len(names) != len(loaded) or not all(names):
                raise NotARun(f"--labels: give {len(loaded)} non-empty names, one per run")
        args.out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=args.out, prefix=".write-probe-"):
            pass  # --out writable, before anything is plotted
    except (NotARun, OSError) as e:
        if args.debug:
            raise
        from mpcpearl_jax.cli.errors import error_line

        print(f"error: {error_line(e)}", file=sys.stderr)
        return 2
    plot_learning_curves(
        [(name, rows) for name, (_, _, rows, _) in zip(names, loaded, strict=True)],
        args.out / "curves.png",
    )
    finished = [
        (name, res) for name, (_, _, _, res) in zip(names, loaded, strict=True) if res is not None
    ]
    paper = finished[0][1].get("paper", {}) if finished else {}
    text = comparison_table(finished, paper)
    if gp is not None:
        text += "\n\nGP-MPC (this project, same test tasks): " + ", ".join(
            f"{k} {gp[k]:.2f}" for k in METRIC_NAMES if isinstance(gp.get(k), (int, float))
        )
    notes = {res["paper_note"] for _, res in finished if res.get("paper_note")}
    text += "".join(f"\n\n{note}" for note in sorted(notes))
    (args.out / "table.md").write_text(text + "\n")
    summary = {
        "runs": [
            {
                "run": str(r),
                "label": name,
                "iterations": rows[-1]["iteration"] if rows else 0,
                "gradient_steps_per_seed": (rows[-1]["iteration"] if rows else 0)
                * c.get("train", c.get("grbal", {}))["updates_per_iteration"],
                "seeds": c["seeds"],
                "wall_s": rows[-1].get("wall_s") if rows else None,
                "results": res,
            }
            for name, (r, c, rows, res) in zip(names, loaded, strict=True)
        ]
    }
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
