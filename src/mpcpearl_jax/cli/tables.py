"""What the commands print beside their progress: Markdown tables, the line of a written record,
a time budget's eval points and its summary, a run's results table."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mpcpearl_jax.training import machine


def print_table(rows: Sequence[dict[str, Any]], columns: Sequence[str], title: str = "") -> str:
    """Print rows as a Markdown table (`training.machine.format_table`; also returned)."""
    text = machine.format_table(rows, columns, title)
    print(text, flush=True)
    return text


def write_record(name: str, config: dict[str, Any], results: Any, out_dir: str | Path) -> Path:
    """`training.machine.write_record` (out_dir/name.json), and a line naming the file."""
    path = machine.write_record(name, config, results, out_dir)
    print(f"wrote {path}", flush=True)
    return path


def print_point(p: dict) -> None:
    """One line per eval point of a minutes run."""
    print(
        f"[learning] {p['minutes']:7.2f} min  it {p['iteration']:6d}  grad {p['grad_steps']:8d}"
        f"  test SR {p['test_SR']:.2f} CFR {p['test_CFR']:.2f} ret {p['test_return']:8.1f}"
        f"  val SR {p['val_SR']:.2f} CFR {p['val_CFR']:.2f}  (eval {p['eval_s']:.1f} s)",
        flush=True,
    )


def curve_summary(info: dict, label: str, out: Path) -> int:
    """A minutes run's end: the time-to-target table and one line of what it trained; exit 0
    when the budget was spent, 1 when training diverged or no iteration finished."""
    from mpcpearl_jax.training.budget import CURVE_FILE, summary_rows

    record, done = info["curve"], info["iterations"]
    if done == 0:
        print(f"error: no iteration finished; {out / CURVE_FILE} written", file=sys.stderr)
        return 1
    print_table(
        summary_rows(record),
        ["split", "target", "minutes", "grad steps", "iteration"],
        title=f"{label}: time to target (training minutes, compile included)",
    )
    hit = record["time_to"]["train"]["first_success"]
    first = "never" if hit is None else f"{hit['minutes']:.2f} min"
    last, tm = info["points"][-1], record["timing"]
    print(
        f"trained {info['train_s'] / 60:.2f} min ({done} iterations, {record['grad_steps']} "
        f"gradient steps, {record['env_steps']} env steps per seed; first iteration incl. "
        f"compile {info['first_iteration_s']:.1f} s); evaluation {info['eval_s']:.1f} s off the "
        f"clock; first training success: {first}; final test SR {last['test_SR']:.2f}, val SR "
        f"{last['val_SR']:.2f}; total wall {tm['total_wall_s']:.1f} s",
        flush=True,
    )
    print(f"curve, policy and results in {out}", flush=True)
    return 0 if info["stopped"] == "budget" else 1
