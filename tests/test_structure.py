"""The shape of the code that the layer test does not see: one run driver, command lines that
nothing imports, a run session that closes what it opened, a deploy package free of flax."""

from __future__ import annotations

import ast
import dataclasses
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "mpcpearl_jax"


def _calls(path: Path, name: str) -> list[int]:
    """Lines of `path` that call a function or method called `name`."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            f = node.func
            called = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)
            if called == name:
                lines.append(node.lineno)
    return lines


def test_one_run_driver():
    """The training loop has one caller, the run session (`training.run.Session.train`); the
    training command (on iterations or on a time budget) and GrBAL go through the session."""
    callers = {
        str(p.relative_to(ROOT)): _calls(p, "train_loop")
        for tree in ("src", "experiments", "lab", "benchmarks")
        for p in (ROOT / tree).rglob("*.py")
    }
    callers = {p: lines for p, lines in callers.items() if lines}
    assert list(callers) == ["src/mpcpearl_jax/training/run.py"], callers
    for user in ("src/mpcpearl_jax/training/budget.py", "src/mpcpearl_jax/grbal/run.py"):
        text = (ROOT / user).read_text()
        assert "open_session(" in text or ".train(" in text, user
        assert "_sigint_flag" not in text and "Checkpointer(" not in text, user


def _exits(path: Path) -> list[int]:
    """Lines of `path` that end the process: sys.exit, os._exit, exit, quit."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name):
                if (f.value.id, f.attr) in (("sys", "exit"), ("os", "_exit")):
                    lines.append(node.lineno)
            elif isinstance(f, ast.Name) and f.id in ("exit", "quit"):
                lines.append(node.lineno)
    return lines


# the MPC's pool worker processes end themselves (once the training process is gone,
# `watch_parent`; a worker that imported an unguarded main script): a worker's own exit, not a
# command's
WORKER_EXITS = ("src/mpcpearl_jax/mpc/host.py", "src/mpcpearl_jax/mpc/pool.py")


def test_the_library_neither_prints_nor_exits_outside_the_command_layer():
    """Below `mpcpearl_jax.cli` the library reports through callbacks, return values and
    `notices` (a logger): no `print`, and no exit of the process."""
    prints, exits = {}, {}
    for path in SRC.rglob("*.py"):
        rel = str(path.relative_to(ROOT))
        if path.relative_to(SRC).parts[0] == "cli":
            continue
        if _calls(path, "print"):
            prints[rel] = _calls(path, "print")
        if _exits(path) and rel not in WORKER_EXITS:
            exits[rel] = _exits(path)
    assert not prints, prints
    assert not exits, exits
    assert sum(len(_exits(ROOT / p)) for p in WORKER_EXITS if (ROOT / p).exists()) <= 2


def test_the_exit_check_sees_each_way_out(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import os, sys\nsys.exit(1)\nos._exit(2)\nexit()\nprint('x')\n")
    assert _exits(f) == [2, 3, 4] and _calls(f, "print") == [5]


def test_every_training_command_goes_through_the_one_entry():
    """The training commands (restaurant, sidewalk, learning and grbal) are one function,
    `cli.train.main`, given the registered algorithm (`mpcpearl_jax.algorithms`): it trains
    through `mpcpearl_jax.train` (`api.train.train`); no command opens a session or runs a mode
    itself, GrBAL has no entry of its own, and the command layer names no algorithm's package
    (it dispatches on the registered object)."""
    commands = [ROOT / "experiments" / f"{c}.py" for c in ("restaurant", "sidewalk", "learning")]
    commands += [ROOT / "experiments" / "grbal.py", ROOT / "experiments" / "common.py"]
    commands += list((SRC / "cli").rglob("*.py"))
    for path in commands:
        for name in ("open_session", "train_iterations", "train_minutes", "final_evaluation"):
            assert not _calls(path, name), (path.name, name)
    tree = ast.parse((SRC / "cli" / "train.py").read_text())
    bodies = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}
    called = [
        c.func.id
        for c in ast.walk(bodies["main"])
        if isinstance(c, ast.Call) and isinstance(c.func, ast.Name)
    ]
    assert "train" in called
    assert not [name for name in bodies if "grbal" in name.lower()], sorted(bodies)
    assert "mpcpearl_jax.api.train" in {m for _, m in _imported(SRC / "cli" / "train.py")}
    for path in (SRC / "cli").rglob("*.py"):
        assert not [m for _, m in _imported(path) if m.startswith("mpcpearl_jax.grbal")], path
    for name in ("grbal", "restaurant", "sidewalk", "learning"):  # each calls that one main
        assert _calls(ROOT / "experiments" / f"{name}.py", "main"), name
    grbal = ast.parse((SRC / "grbal" / "run.py").read_text())
    assert "train" not in {n.name for n in grbal.body if isinstance(n, ast.FunctionDef)}


def test_experiments_common_only_re_exports():
    """experiments/common.py names the command layer's parts for the experiment commands: its
    body is imports (after its docstring), each from `mpcpearl_jax.cli`, and each name it
    imports is one an experiments module takes from it."""
    path = ROOT / "experiments" / "common.py"
    body = ast.parse(path.read_text()).body
    assert isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
    imports = [n for n in body[1:] if getattr(n, "module", None) != "__future__"]
    assert all(isinstance(n, ast.ImportFrom) for n in imports), [type(n).__name__ for n in imports]
    modules = [n.module for n in imports]
    assert all(m.startswith("mpcpearl_jax.cli") for m in modules), modules
    offered = {a.asname or a.name for n in imports for a in n.names}
    taken: set[str] = set()
    for user in (ROOT / "experiments").glob("*.py"):
        for node in ast.walk(ast.parse(user.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "experiments.common":
                taken |= {a.name for a in node.names}
    assert offered == taken, (sorted(offered - taken), sorted(taken - offered))


def test_the_config_is_validated_once_where_it_is_resolved():
    """The checks across fields (`config.validate`) run in one place, `config.resolve`, which
    every command builds its config with; not again in the commands, the session or the
    trainer."""
    callers = {
        str(p.relative_to(ROOT)): _calls(p, "validate")
        for tree in ("src", "experiments", "examples")
        for p in (ROOT / tree).rglob("*.py")
    }
    assert {p: n for p, n in callers.items() if n} == {
        "src/mpcpearl_jax/config.py": _calls(SRC / "config.py", "validate")
    }
    assert len(callers["src/mpcpearl_jax/config.py"]) == 1
    functions = {
        node.name: node
        for node in ast.walk(ast.parse((SRC / "config.py").read_text()))
        if isinstance(node, ast.FunctionDef)
    }
    # `ExperimentConfig.validated` runs it; `resolve` (the one, for every algorithm's config
    # type) runs `validated` last
    validated, resolve = functions["validated"], functions["resolve"]
    assert validated.lineno <= callers["src/mpcpearl_jax/config.py"][0] <= validated.end_lineno
    calls = [
        n.lineno
        for n in ast.walk(resolve)
        if isinstance(n, ast.Call)
        and isinstance(n.func, ast.Attribute)
        and n.func.attr == "validated"
    ]
    assert len(calls) == 1


def _imported(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import statement in `path`, function-level ones included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
    return found


def _offenders(trees, packages: tuple[str, ...]) -> list[str]:
    return [
        f"{path.relative_to(ROOT)}:{line} {m}"
        for tree in trees
        for path in tree.rglob("*.py")
        for line, m in _imported(path)
        if m.split(".")[0] in packages
    ]


def test_nothing_imports_a_command_line_module():
    """Library modules and benchmarks never import from experiments/ or lab/ (command lines
    parse arguments, call the library and print; the lab's screens, campaigns, tables and
    diagnostics sit on top of both)."""
    offenders = _offenders((SRC, ROOT / "benchmarks"), ("experiments", "lab"))
    assert not offenders, offenders


def test_the_user_commands_do_not_import_the_lab():
    """experiments/ holds the commands a user runs; none of them needs lab/."""
    offenders = _offenders((ROOT / "experiments",), ("lab",))
    assert not offenders, offenders


def test_offenders_finds_an_import_of_the_lab(tmp_path, monkeypatch):
    """The import checks above see top-level and function-level imports."""
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "m.py").write_text("import os\ndef f():\n    from lab.tables import render\n")
    assert _offenders((tmp_path,), ("lab",)) == ["m.py:3 lab.tables"]


def test_the_lab_stands_on_the_library_alone():
    """lab/ (screens, campaigns, tables, diagnostics) imports neither benchmarks/ nor
    experiments/: it calls the library (the command layer `mpcpearl_jax.cli` included) and its
    own `lab.harness`, as a user's script would."""
    offenders = _offenders((ROOT / "lab",), ("benchmarks", "experiments"))
    assert not offenders, offenders


def test_both_trainers_follow_the_trainer_protocol():
    """MPC-PEARL's and GrBAL's trainers have every member of `training.protocol.TrainerProtocol`
    (what the session, the loop, the minutes mode and the end of a run use), its methods with
    the protocol's parameters in its order."""
    import inspect
    import typing

    from mpcpearl_jax.grbal.trainer import GrbalTrainer
    from mpcpearl_jax.training.protocol import TrainerProtocol
    from mpcpearl_jax.training.trainer import Trainer

    attrs = set(typing.get_type_hints(TrainerProtocol, include_extras=False)) - {"return"}
    methods = [m for m in ("init_state", "iteration", "evaluate") if hasattr(TrainerProtocol, m)]
    assert attrs == {"cfg", "env", "train_tasks", "test_tasks", "horizon"} and len(methods) == 3
    for cls in (Trainer, GrbalTrainer):
        init = ast.parse(inspect.getsource(cls))
        assigned = {
            t.attr
            for n in ast.walk(init)
            if isinstance(n, ast.Assign)
            for t in n.targets
            if isinstance(t, ast.Attribute) and getattr(t.value, "id", None) == "self"
        }
        assert attrs <= assigned, (cls.__name__, attrs - assigned)
        for m in methods:
            want = list(inspect.signature(getattr(TrainerProtocol, m)).parameters)
            got = list(inspect.signature(getattr(cls, m)).parameters)
            assert got[: len(want)] == want, (cls.__name__, m, got)


class _Closable:
    def __init__(self, log, name):
        self.log, self.name = log, name

    def close(self):
        self.log.append(self.name)

    release = close


class _State:
    iteration = [0]


def test_session_close_closes_trainer_checkpointer_tensorboard_and_lock(tmp_path):
    from mpcpearl_jax.config import preset
    from mpcpearl_jax.training.run import Session

    log: list[str] = []
    sess = Session(
        preset("smoke"),
        tmp_path,
        _Closable(log, "trainer"),
        _State(),
        ckpt=_Closable(log, "ckpt"),
        lock=_Closable(log, "lock"),
        tb=_Closable(log, "tb"),
    )
    with sess:
        pass
    assert sorted(log) == ["ckpt", "lock", "tb", "trainer"]
    sess.close()  # a second close does not close the lock, checkpointer or TensorBoard again
    assert sorted(log) == ["ckpt", "lock", "tb", "trainer", "trainer"]


def test_trainer_close_shuts_the_bridge_worker_pool():
    """The MPC bridge's worker processes end with the trainer (`Trainer.close`), and a later
    solve would start them again."""
    from mpcpearl_jax.config import preset
    from mpcpearl_jax.training.trainer import Trainer

    cfg = preset("smoke")
    cfg = cfg.replace(train=dataclasses.replace(cfg.train, eps=0.2))
    trainer = Trainer(cfg)
    assert trainer.bridge is not None
    shut = []

    class Pool:
        def shutdown(self):
            shut.append(True)

    trainer.bridge.host._pool = Pool()
    trainer.close()
    assert shut == [True] and trainer.bridge.host._pool is None


def test_load_exported_imports_neither_flax_nor_orbax():
    code = (
        "import sys\n"
        "from mpcpearl_jax.deploy import load_exported\n"
        "bad = [m for m in ('flax', 'orbax', 'optax', 'distrax') if m in sys.modules]\n"
        "assert not bad, bad\n"
        "import mpcpearl_jax\n"
        "assert callable(mpcpearl_jax.load_policy) and callable(mpcpearl_jax.make_env)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]


def test_one_resolve_for_every_algorithm():
    """A run's config is built by one `resolve` (`mpcpearl_jax.config`), for MPC-PEARL and
    GrBAL alike (their config types' `from_preset`): no other module of the package defines
    one."""
    defining = [
        str(p.relative_to(SRC))
        for p in SRC.rglob("*.py")
        for node in ast.parse(p.read_text()).body
        if isinstance(node, ast.FunctionDef) and node.name == "resolve"
    ]
    assert defining == ["config.py"]
