"""No arrow runs back up: every import inside the package goes to a module of the same or a
lower layer (checked on the source, function-level imports included)."""

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "mpcpearl_jax"

# lowest first; a module is ranked by its longest listed prefix (modules not listed are not
# checked)
LAYERS = [
    ["errors", "validate", "dynamics", "runlock", "resources"],
    ["physics", "metrics", "pearl.types", "pearl.config", "mpc.config"],
    ["envs", "pearl.networks", "pearl.losses", "pearl.learner", "pearl.buffers", "pearl"],
    ["mpc", "shield"],
    ["collect", "evaluate", "config", "grbal.config", "grbal.model", "grbal.planner"],
    ["trainer", "checkpoint", "grbal.trainer"],
    ["run", "report", "livelog", "animate", "viz", "grbal.run", "grbal"],
]
RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def _rank(module: str) -> int | None:
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in RANK:
            return RANK[".".join(parts[:n])]
    return None


def _modules():
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).with_suffix("")
        parts = [p for p in rel.parts if p != "__init__"]
        if parts:
            yield ".".join(parts), path


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "mpcpearl_jax":
                yield from (a.name for a in node.names)
            elif node.module.startswith("mpcpearl_jax."):
                base = node.module.removeprefix("mpcpearl_jax.")
                yield base
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("mpcpearl_jax."):
                    yield a.name.removeprefix("mpcpearl_jax.")


@pytest.mark.parametrize("module,path", list(_modules()), ids=lambda x: str(x))
def test_no_import_from_a_lower_layer_to_a_higher_one(module, path):
    own = _rank(module)
    if own is None:
        pytest.skip(f"{module} is not placed in a layer")
    up = [m for m in _imports(path) if (_rank(m) or 0) > own]
    assert not up, f"{module} (layer {own}) imports from higher layers: {up}"


def test_the_knots_of_issue_11_stay_untied():
    text = {m: p.read_text() for m, p in _modules()}
    assert "mpcpearl_jax.envs" not in text["checkpoint"]
    assert "mpcpearl_jax.envs" not in text["physics"]
    for m in ("config", "pearl.config", "mpc.config", "grbal.config"):
        assert "envs.types import ConfigError" not in text[m], m
    for m in ("pearl.buffers", "collect", "evaluate"):
        assert "pearl.learner" not in text[m], m
    assert 'cfg.env == "sidewalk"' not in text["run"]
    assert "except ImportError" not in text["envs"]
