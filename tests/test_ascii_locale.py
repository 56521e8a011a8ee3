"""Every command under an ASCII locale (PYTHONIOENCODING=ascii): its --help (and the training
commands' --help-config) print, the characters ASCII lacks (the help's "§", a folder's name)
written as escapes, never a UnicodeEncodeError."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESTAURANT_RUN = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2"


def _commands() -> list[str]:
    """Every module of experiments/, lab/ and benchmarks/ that runs as a program."""
    mods = []
    for folder in ("experiments", "lab", "lab/diagnostics", "benchmarks"):
        for path in sorted((ROOT / folder).glob("*.py")):
            if '__name__ == "__main__"' in path.read_text():
                mods.append(".".join((*Path(folder).parts, path.stem)))
    return mods


def _described_by_docstring(module: str) -> str | None:
    """The first paragraph of a command's docstring, whitespace-normalised and as the ASCII
    locale escapes it, when the command's parser takes its description from the docstring."""
    path = ROOT.joinpath(*module.split(".")).with_suffix(".py")
    source = path.read_text()
    if "description=__doc__" not in source and "common_parser(__doc__" not in source:
        return None
    lead = ast.get_docstring(ast.parse(source), clean=True).split("\n\n")[0]
    return " ".join(lead.encode("ascii", "backslashreplace").decode().split())


# One process for every command: before each, the project's modules are dropped (so the command
# imports the command layer afresh, as it does on its own) and stdout and stderr are new strict
# ASCII streams, as PYTHONIOENCODING=ascii gives a fresh process.
DRIVER = r"""
import io, json, os, runpy, sys
results = {}
for argv in json.loads(sys.argv[1]):
    for name in [m for m in sys.modules if m.split(".")[0] in ("experiments", "lab", "benchmarks")
                 or m.startswith("mpcpearl_jax.cli")]:
        del sys.modules[name]
    out, err = io.BytesIO(), io.BytesIO()
    sys.stdout = io.TextIOWrapper(out, encoding="ascii", errors="strict", write_through=True)
    sys.stderr = io.TextIOWrapper(err, encoding="ascii", errors="strict", write_through=True)
    sys.argv = list(argv)
    try:
        runpy.run_module(argv[0], run_name="__main__", alter_sys=True)
        code = None
    except SystemExit as e:
        code = e.code
    except BaseException as e:
        code = f"{type(e).__name__}: {e}"
    results[" ".join(argv)] = [code, out.getvalue().decode(), err.getvalue().decode()]
sys.__stdout__.write(json.dumps(results))
"""


def _run(argvs: list[list[str]]) -> dict:
    env = dict(os.environ, PYTHONIOENCODING="ascii", PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", DRIVER, json.dumps(argvs)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def test_every_commands_help_prints_under_an_ascii_locale():
    mods = _commands()
    assert {"experiments.restaurant", "lab.diagnostics.dagger", "benchmarks.memory"} <= set(mods)
    argvs = [[m, "--help"] for m in mods]
    argvs += [[m, "--help-config"] for m in ("experiments.restaurant", "experiments.sidewalk")]
    bad, cut = {}, {}
    for argv, (code, out, err) in _run(argvs).items():
        if code not in (0, None) or "Error" in err or not out.strip():
            bad[argv] = (code, err[-300:])
        lead = _described_by_docstring(argv.split()[0])
        if argv.endswith("--help") and lead and lead not in " ".join(out.split()):
            cut[argv] = lead[-60:]
    assert not bad, bad
    # a command whose help is its docstring's lead prints the whole first paragraph, not its
    # first line cut mid-sentence
    assert not cut, cut
    helped = _run([["experiments.restaurant", "--help"]])["experiments.restaurant --help"]
    assert "\\xa7" in helped[1]  # the "§" as an escape, the rest of the help as written


def test_evaluate_into_a_folder_named_outside_ascii(tmp_path):
    """The results table and the folder's name print under an ASCII locale (the name escaped),
    after results.json is written; exit code 0."""
    out = tmp_path / "r\u00e9sultats"
    argv = ["experiments.evaluate", str(RESTAURANT_RUN), "--tasks", "0", "--figures", "none"]
    ((code, stdout, err),) = _run([[*argv, "--out", str(out)]]).values()
    assert code in (0, None), err[-2000:]
    assert "UnicodeEncodeError" not in err
    assert json.loads((out / "results.json").read_text())["metrics"]
    assert "r\\xe9sultats" in stdout
