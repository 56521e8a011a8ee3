"""pyproject.toml names one minimum Python version: the package's requires-python, ruff's
target-version and mypy's python_version agree, and the interpreter running the tests meets it
(`typing.Self` in mpcpearl_jax.config and current JAX releases need 3.11)."""

import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)


def _minimum_python() -> tuple[int, int]:
    spec = _pyproject()["project"]["requires-python"]
    match = re.fullmatch(r">=\s*(\d+)\.(\d+)", spec)
    assert match, f"requires-python {spec!r}: expected '>=X.Y'"
    return int(match[1]), int(match[2])


def test_requires_python_ruff_and_mypy_name_the_same_minimum():
    major, minor = _minimum_python()
    tools = _pyproject()["tool"]
    assert tools["ruff"]["target-version"] == f"py{major}{minor}"
    assert tools["mypy"]["python_version"] == f"{major}.{minor}"


def test_the_running_interpreter_meets_requires_python():
    assert sys.version_info[:2] >= _minimum_python(), sys.version


def test_the_license_file_is_the_one_pyproject_declares():
    license_ = _pyproject()["project"]["license"]
    assert license_ == {"text": "MIT"}
    assert (ROOT / "LICENSE").read_text().startswith("MIT License\n")
