"""One evaluation of a trained run in a process of its own, as a campaign runs it:
`mpcpearl_jax.evaluate` with the keyword arguments of one JSON object (the run folder under
"run"; `shield` true, or those fields of a ShieldConfig that differ from its defaults).

    python -m lab.evaluation '{"run": "results/restaurant/main-default", "split": "val",
                               "task_seeds": "1-8", "figures": "none", "out": "..."}'

A campaign entry names its evaluations with the evaluation command's flags
(`python -m experiments.evaluate RUN ARGS...`); `keywords` reads them, once, as these keyword
arguments (only those that differ from the defaults), and `command` is the process that runs
them. It prints a line per task set and one with the metrics once results.json is written;
a bad argument is one line naming its flag (exit 2), a stop signal one line (exit 128 + the
signal; nothing is written before the end, so the same evaluation starts again).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mpcpearl_jax.cli.stopping import stops_with

MODULE = "lab.evaluation"


def _jsonable(value: Any) -> Any:
    """An evaluation option as JSON holds it: paths as text, a ShieldConfig as the fields that
    differ from the defaults ({} for the default shield)."""
    import dataclasses

    from mpcpearl_jax.mpc.shield import ShieldConfig

    if isinstance(value, Path):
        return str(value)
    if isinstance(value, ShieldConfig):
        default = ShieldConfig()
        return {
            f.name: _jsonable(getattr(value, f.name))
            for f in dataclasses.fields(value)
            if getattr(value, f.name) != getattr(default, f.name)
        }
    if isinstance(value, tuple):
        return [_jsonable(v) for v in value]
    return value


def keywords(run: Path, args: Sequence[str]) -> dict[str, Any]:
    """`mpcpearl_jax.evaluate`'s keyword arguments (JSON values, the defaults left out) that the
    evaluation command's flags `args` give for the run folder `run`, "run" included; ValueError
    with the command's message for a flag it does not take, or options that exclude each other
    (read by the command's parser: nothing is opened or run)."""
    from mpcpearl_jax.api.evaluate import EvaluationOptions
    from mpcpearl_jax.cli.evaluate import make_parser, options

    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            parsed = make_parser().parse_args([str(run), *args])
            given = options(parsed)
    except SystemExit:
        raise ValueError((err.getvalue().strip().splitlines() or ["bad arguments"])[-1]) from None
    given |= {"out": parsed.out, "overwrite": parsed.overwrite}
    defaults = EvaluationOptions()
    out: dict[str, Any] = {"run": str(run)}
    for name, value in given.items():
        value = _jsonable(value)
        if value != _jsonable(getattr(defaults, name)):
            out[name] = value
    return out


def command(kw: dict[str, Any]) -> list[str]:
    """The process that runs the evaluation of the keyword arguments `kw` (`keywords`)."""
    return [sys.executable, "-m", MODULE, json.dumps(kw)]


def record(kw: dict[str, Any]) -> Path:
    """The record the evaluation of `kw` writes (its results.json)."""
    return Path(kw["out"]) / "results.json"


def decode(text: str) -> tuple[str | None, dict[str, Any]]:
    """(the run folder, the other keyword arguments) of a JSON object (module doc); ValueError
    for anything else."""
    from mpcpearl_jax.mpc.shield import ShieldConfig

    kw = json.loads(text)
    if not isinstance(kw, dict):
        raise ValueError(f"expected a JSON object of keyword arguments, got {text[:60]!r}")
    if isinstance(kw.get("shield"), dict):
        given: dict[str, Any] = {
            k: tuple(v) if isinstance(v, list) else v for k, v in kw["shield"].items()
        }
        kw["shield"] = ShieldConfig(**given)
    return kw.pop("run", None), kw


def _summary(ev: Any) -> str:
    """One line: what was evaluated and its metrics (pooled: mean +- standard error)."""
    s, rec = ev.setup, ev.record
    if "pooled" in rec:
        where = f"task seeds {','.join(map(str, rec['task_seeds']))}, {rec['num_tasks']} tasks"
        numbers = ", ".join(
            f"{k} {v['mean']:.2f} +- {v['se']:.2f}" for k, v in rec["pooled"].items()
        )
    else:
        source = "the paper's scenarios" if s.scenarios else f"task seed {s.task_seed}"
        where = f"{source}, {len(s.task_ids)} tasks"
        numbers = ", ".join(f"{k} {v:.2f}" for k, v in rec["metrics"].items())
    return f"[evaluate] {s.label}: {s.env_name}/{s.split} ({where}): {numbers}"


@stops_with("interrupted before the evaluation finished (nothing written); run it again")
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=f"python -m {MODULE}", description=__doc__.split("\n\n")[0])
    p.add_argument("keywords", help="mpcpearl_jax.evaluate's keyword arguments (a JSON object)")
    args = p.parse_args(argv)
    import mpcpearl_jax
    from mpcpearl_jax.cli.errors import one_line_errors
    from mpcpearl_jax.cli.evaluate import flags
    from mpcpearl_jax.cli.platform import check_platform

    def task_set(ts: int, rec: dict) -> None:
        m = rec["metrics"]
        n = len(rec["tasks"])
        print(f"[evaluate] task seed {ts}: {n} task(s), SR {m['SR']:.2f} CFR {m['CFR']:.2f}")

    with one_line_errors(interrupted=None) as failed:
        try:
            run, kw = decode(args.keywords)
        except (ValueError, TypeError) as e:
            raise ValueError(f"{MODULE}: {e}") from None
        check_platform()
        with flags():  # an argument named as the evaluation command's flag
            ev = mpcpearl_jax.evaluate(run, on_task_set=task_set, **kw)
    if failed.code is not None:
        return failed.code
    print(_summary(ev), flush=True)  # results.json is written
    print(f"[evaluate] wrote {', '.join(map(str, ev.written))}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
