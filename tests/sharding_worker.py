"""One training process of tests/test_sharding.py and benchmarks/scaling.py, run in a subprocess
(the device count is fixed when JAX starts: XLA_FLAGS=--xla_force_host_platform_device_count=N).

`python tests/sharding_worker.py RESULT.npz [experiments.restaurant options]` trains like the
command line (the same options, including --devices, --coordinator, --num-processes,
--process-id; --iterations and --resume), evaluates on the test tasks, and (process 0) writes
every seed's parameters, the per-seed metrics (first EVAL_TASKS test tasks), the MPC rows solved
and the devices used into RESULT.npz.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

import jax

from mpcpearl_jax.cli.args import build_config, parser

EVAL_TASKS = 6


def main(argv: list[str]) -> int:
    result = Path(argv[0])
    args = parser("restaurant").parse_args(argv[1:])
    from mpcpearl_jax.distributed import first_local, initialize, is_primary, to_host

    initialize(args.coordinator, args.num_processes, args.process_id)
    cache = os.environ.get("MPCPEARL_TEST_JAX_CACHE") or os.path.join(
        tempfile.gettempdir(), "mpcpearl_jax_test_xla_cache"
    )
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    from mpcpearl_jax.training.run import open_session, train_iterations

    cfg = build_config(args, "restaurant")
    with open_session(cfg, args.out, resume=args.resume) as sess:
        sess_rows, trainer = sess.rows, sess.trainer
        state, _ = train_iterations(sess)
    # the first EVAL_TASKS test tasks (seconds instead of a minute on a 2-core CPU)
    tasks = jax.tree_util.tree_map(lambda x: x[:EVAL_TASKS], trainer.test_tasks)
    ev = trainer.evaluate(state, tasks=tasks)
    params = to_host(state.learner.params)
    if is_primary():
        import numpy as np

        flat = {
            "/".join(str(getattr(k, "key", k)) for k in path): np.asarray(v)
            for path, v in jax.tree_util.tree_flatten_with_path(params)[0]
        }
        mesh = trainer.mesh
        meta = {
            "eval": ev,
            "devices": 1 if mesh is None else int(mesh.devices.size),
            "processes": jax.process_count(),
            "iteration": int(first_local(state.iteration)),
            "mpc_rows": [r.get("mpc_rows", 0) for r in sess_rows],
        }
        np.savez(result, meta=json.dumps(meta), **flat)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
