"""A pool that cannot start says so (`mpc.pool`): a script that starts the MPC's worker pool from
top-level code without `if __name__ == "__main__":` gets one error naming the guard, before any
worker starts (`main_unguarded`) or, where that cannot be seen (the pool started from a thread),
as soon as the workers that re-ran the script exit (`check_started`): never a rollout of
fallbacks."""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import pytest

from mpcpearl_jax.errors import WorkerPoolError
from mpcpearl_jax.mpc import pool
from mpcpearl_jax.mpc.pool import _guarded, main_unguarded, pool_size

ROOT = Path(__file__).resolve().parents[1]
GUARD = 'if __name__ == "__main__":'


def _line(source: str, text: str) -> int:
    return next(i for i, s in enumerate(source.splitlines(), 1) if text in s)


@pytest.mark.parametrize(
    "source, guarded",
    [
        ("import x\nrun()\n", False),
        ('import x\nif __name__ == "__main__":\n    run()\n', True),
        ("if '__main__' == __name__:\n    run()\n", True),
        ('if __name__ != "__main__":\n    pass\nelse:\n    run()\n', True),
        ('if __name__ == "__main__":\n    pass\nelse:\n    run()\n', False),
        ('try:\n    if __name__ == "__main__":\n        run()\nexcept OSError:\n    pass\n', True),
        ('with ctx():\n    if __name__ == "__main__":\n        run()\n', True),
        ("if verbose:\n    run()\n", False),
    ],
)
def test_guarded_sees_the_main_guard_around_a_line(source, guarded):
    assert _guarded(ast.parse(source).body, _line(source, "run()")) is guarded


def test_main_unguarded_names_the_scripts_line_that_runs_top_level(tmp_path, monkeypatch):
    """The main module's top-level frame on the stack, outside the guard: (script, line)."""
    script = tmp_path / "user.py"
    for source, want in (
        ("import os\nfound = where()\n", 2),
        ('def main():\n    return where()\nif __name__ == "__main__":\n    found = main()\n', None),
    ):
        script.write_text(source)
        main = types.ModuleType("__main__")
        main.__file__ = str(script)
        main.where = main_unguarded
        monkeypatch.setitem(sys.modules, "__main__", main)
        exec(compile(source, str(script), "exec"), vars(main))
        assert main.found == (None if want is None else (str(script), want))
    assert main_unguarded() is None  # pytest's own main module: guarded or not a script


def _run(tmp_path: Path, body: str, timeout: float) -> tuple[subprocess.CompletedProcess, float]:
    script = tmp_path / "user_script.py"
    script.write_text(textwrap.dedent(body))
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=tmp_path,
    )
    return proc, time.perf_counter() - t0


def _one_error(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 1, (proc.returncode, proc.stdout, proc.stderr[-3000:])
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("mpcpearl_jax.errors.WorkerPoolError:"), proc.stderr[-3000:]
    assert GUARD in last and "mpc.n_workers=1" in last and "user_script.py" in last
    return last


@pytest.mark.skipif(pool_size(2) < 2, reason="one core: mpc.n_workers=2 makes no pool")
def test_a_script_without_the_main_guard_gets_one_error_before_any_worker_starts(tmp_path):
    """The user's case: GP-MPC's bridge with a pool of 2, built at a script's top level, no guard.
    The rollout's first trace starts the pool (`MPCBridge.init`), which refuses at once."""
    body = """
        import multiprocessing
        from mpcpearl_jax.envs import make_env
        from mpcpearl_jax.mpc import MPCConfig, make_mpc_bridge

        bridge = make_mpc_bridge(make_env("restaurant"), MPCConfig(n_workers=2))
        try:
            bridge.init(4)
        finally:
            print("children", len(multiprocessing.active_children()), flush=True)
        """
    proc, _ = _run(tmp_path, body, timeout=120)
    line = _line(textwrap.dedent(body), "bridge.init")
    assert f"user_script.py (line {line})" in _one_error(proc)
    assert "children 0" in proc.stdout  # no worker was started


@pytest.mark.slow
@pytest.mark.skipif(pool_size(2) < 2, reason="one core: mpc.n_workers=2 makes no pool")
def test_a_pool_started_from_a_thread_without_the_guard_fails_on_its_first_call(tmp_path):
    """Started from a thread the parent cannot see the script's line; its workers, which import the
    script again, exit (`UNGUARDED_EXIT`) and the first call raises the same error instead of
    falling back."""
    proc, wall = _run(
        tmp_path,
        """
        import threading
        import numpy as np
        from mpcpearl_jax.envs import make_env
        from mpcpearl_jax.mpc import HostSolver, MPCConfig, RowProblem

        cfg = MPCConfig(n_workers=2, worker_timeout_s=240)  # the workers' imports are not timed
        host = HostSolver(make_env("restaurant").config, cfg)
        box = np.array([[3.0, 3.5]])
        rows = [
            RowProblem(np.array([x, 0.0, 0.0]), np.array([4.0, 0.0]), np.zeros((10, 2, 100, 2)),
                       np.zeros(2, bool), box, box, np.ones(1))
            for x in (-4.0, -3.0)
        ]
        raised = []

        def solve():
            try:
                host.solve_rows(rows, [None, None], 1)
            except Exception as e:
                raised.append(e)

        t = threading.Thread(target=solve)
        t.start()
        t.join()
        host.close()
        print("solved", not raised, flush=True)
        if raised:
            raise raised[0]
        """,
        timeout=300,
    )
    _one_error(proc)
    assert "solved False" in proc.stdout and wall < 240


def test_a_worker_that_exited_unguarded_turns_into_the_error(monkeypatch):
    """`check_started` on a broken pool: a worker's exit status `UNGUARDED_EXIT` raises, any
    other (a worker killed during a solve) does not."""

    class Proc:
        def __init__(self, code):
            self.exitcode = code

    class Pool:
        def __init__(self, *codes):
            self._processes = {i: Proc(c) for i, c in enumerate(codes)}

    pool.check_started(Pool(-9, -15), 2)  # killed: the rows fall back, no error
    with pytest.raises(WorkerPoolError, match=r'if __name__ == "__main__":'):
        pool.check_started(Pool(pool.UNGUARDED_EXIT, -15), 2)
