"""No arrow runs back up: every import inside the package goes to a module of the same or a
lower layer (checked on the source, function-level imports included)."""

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "mpcpearl_jax"

# lowest first; every module of the package is ranked, by its longest listed prefix (a
# package's name ranks its modules not listed on their own). The packages are the layers:
# envs < pearl, mpc < collection < config < runfolder < evaluation < training < grbal
# < algorithms < deploy < api < cli, the command layer on top (the commands' stop signals,
# errors, tables and parsers). Collection (episodes with event-triggered MPC infusion) sits
# below both training and evaluation, which import it downward (the trainer, and the evaluation
# command's policy with MPC infusion); the run folder's files (`runfolder`) below every reader of
# a run folder; GrBAL trains on training's run session; `algorithms` registers both above them.
LAYERS = [
    ["errors", "validate", "distributed", "notices", "compilation_cache"],
    ["envs.types", "envs.dynamics", "envs.physics", "pearl.types", "pearl.config", "mpc.config"],
    ["envs", "pearl", "evaluation.metrics"],
    ["mpc", "collection"],
    ["config"],
    ["runfolder"],
    ["evaluation"],
    ["training"],
    ["grbal"],
    ["algorithms"],  # one registered object per algorithm (MPC-PEARL, GrBAL)
    ["deploy"],
    ["api"],  # the entries, for runs of every algorithm: `mpcpearl_jax.train`, `.evaluate`
    ["cli"],  # the command layer: nothing below imports it
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
    assert own is not None, f"{module} is in no layer: place it in LAYERS"
    up = [m for m in _imports(path) if (_rank(m) or 0) > own]
    assert not up, f"{module} (layer {own}) imports from higher layers: {up}"


def test_every_module_is_in_a_layer():
    unplaced = [m for m, _ in _modules() if _rank(m) is None]
    assert not unplaced, f"modules in no layer: {unplaced}"


def test_collection_sits_below_training_and_evaluation():
    """Both the trainer and the evaluation command's runners collect episodes through
    `collection`, downward; no module of the evaluation package imports training."""
    assert RANK["collection"] < RANK["evaluation"] < RANK["training"]
    evaluation = [(m, p) for m, p in _modules() if m.split(".")[0] == "evaluation"]
    assert evaluation and all(_rank(m) <= RANK["evaluation"] for m, _ in evaluation)
    for m, path in evaluation:
        assert not [i for i in _imports(path) if i.split(".")[0] == "training"], m


def test_the_knots_of_issue_11_stay_untied():
    text = {m: p.read_text() for m, p in _modules()}
    assert "mpcpearl_jax.envs" not in text["training.checkpoint"]
    assert "mpcpearl_jax.envs" not in text["runfolder"]
    assert "mpcpearl_jax.envs" not in text["envs.physics"]
    for m in ("config", "pearl.config", "mpc.config", "grbal.config"):
        assert "envs.types import ConfigError" not in text[m], m
    for m in ("pearl.buffers", "collection", "evaluation.evaluate"):
        assert "pearl.learner" not in text[m], m
    assert 'cfg.env == "sidewalk"' not in text["training.run"]
    assert "except ImportError" not in text["envs"]


def test_the_command_layer_is_the_top_floor():
    """`cli` ranks above every other module, and no module outside it imports it (the library
    reports through callbacks, return values and `notices`; the commands print)."""
    assert RANK["cli"] == max(RANK.values())
    assert [m for m in RANK if RANK[m] == RANK["cli"]] == ["cli"]
    below = [(m, p) for m, p in _modules() if m.split(".")[0] != "cli"]
    assert below and all((_rank(m) or 0) < RANK["cli"] for m, _ in below)
    for m, path in below:
        assert not [i for i in _imports(path) if i.split(".")[0] == "cli"], m


def test_training_and_grbal_are_floors_and_only_algorithms_knows_both():
    """Each package is one floor (no module ranked apart from its package above `config`):
    GrBAL trains on training's session, nothing in training imports grbal, and the entries
    dispatch on the registered algorithm (`algorithms`) instead of naming either."""
    assert RANK["training"] < RANK["grbal"] < RANK["algorithms"] < RANK["api"]
    apart = [m for m in RANK if "." in m and RANK[m] > RANK["config"]]
    assert not apart, apart
    for m, path in _modules():
        if m.split(".")[0] == "training":
            assert not [i for i in _imports(path) if i.split(".")[0] == "grbal"], m
