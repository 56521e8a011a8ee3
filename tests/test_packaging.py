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


def test_brax_and_tensorboardx_are_optional_extras_that_dev_includes():
    """The light install leaves out brax (it pulls in mujoco, flask, trimesh, ...) and
    tensorboardX; the `dev` extra brings both, so the suite tests the adapter and --tensorboard."""
    project = _pyproject()["project"]
    names = [re.split(r"[<>=!~\[ ]", d, maxsplit=1)[0].lower() for d in project["dependencies"]]
    assert "brax" not in names and "tensorboardx" not in names
    extras = project["optional-dependencies"]
    assert [d.split(">")[0] for d in extras["brax"]] == ["brax"]
    assert [d.split(">")[0] for d in extras["tensorboard"]] == ["tensorboardX"]
    assert {"brax", "tensorboardX"} <= {d.split(">")[0] for d in extras["dev"]}


def test_the_brax_adapter_without_brax_says_how_to_install_it(monkeypatch):
    import importlib

    import pytest

    for name in [m for m in sys.modules if m == "brax" or m.startswith("brax.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "brax", None)  # `import brax...` raises ImportError
    monkeypatch.delitem(sys.modules, "mpcpearl_jax.envs.brax_adapter", raising=False)
    with pytest.raises(ImportError) as e:
        importlib.import_module("mpcpearl_jax.envs.brax_adapter")
    msg = str(e.value)
    assert "\n" not in msg and 'pip install -e ".[brax]"' in msg
    monkeypatch.delitem(sys.modules, "mpcpearl_jax.envs.brax_adapter", raising=False)
