"""mpcpearl_jax: MPC-PEARL (meta-RL with event-triggered risk-aware MPC infusion) in JAX.

Public entry points: `make_env`, `make_tasks` (environments), `train` (a run from a config:
`train(cfg, out, minutes=None, options=None) -> (state, results)`, the one entry the training
commands use too, `api.train`; `options`: `training.options.TrainOptions`; it trains every
registered algorithm, `algorithms`), `evaluate` (a run folder or loaded
policies, or GP-MPC, on a task source -> the results the evaluation command prints and writes;
`api.evaluate`), `load_policy` (a trained policy
from a run directory), `metrics`; `Adapter`, `Frame`, `Scene`, `observe` (a policy in your own
control loop, from raw sensor arrays), `export_policy` and `load_exported` (a portable artifact
run with jax alone).

The packages mirror the layers (lowest first; `tests/test_layers.py` checks that no import runs
back up):

- `envs`: the robot (dynamics, physics), the navigation env and the task families;
- `pearl`, `mpc`: the learner (networks, losses, buffers) and the risk-aware MPC (GP, SQP,
  the host bridge, the safety shield); `collection`: episodes with event-triggered MPC
  infusion, for training and evaluation;
- `config`: the experiment configuration, its presets and `resolve`;
- `evaluation`: meta-test rollouts (Algorithm 2), the method's metrics, the controller runners,
  tables and figures;
- `training`: the trainer (Algorithm 1), the run session (checkpoints, logs, Ctrl-C) and the
  one training loop, a trained run's final evaluation (`training.final`: results.json,
  figures);
- `grbal`: the GrBAL baseline on the same session;
- `algorithms`: one registered object per algorithm (MPC-PEARL and its baselines, GrBAL): its
  config type and presets, trainer, training rules, final evaluation, progress line and
  evaluation setup, on which the entries and the commands dispatch;
- `deploy`: a trained policy in your own code (`load_policy`, `Adapter`, `export_policy`,
  `load_exported`);
- `api`: the entries, for runs of every algorithm (`train`, `evaluate`);
- `cli`: the command layer on top (stop signals, the error ladder, parsers, the progress bar and
  printed tables, the training commands). Below it nothing prints: the library reports through
  callbacks, return values and the `mpcpearl_jax` logger (`notices`).
"""

from typing import Any

__version__ = "0.1.0"

__all__ = [
    "Adapter",
    "Frame",
    "Scene",
    "evaluate",
    "export_policy",
    "load_exported",
    "load_policy",
    "make_env",
    "make_tasks",
    "metrics",
    "observe",
    "train",
    "__version__",
]

# every name is loaded on first use: `from mpcpearl_jax.deploy import load_exported` pulls in
# jax alone (no flax, no orbax)
_LAZY = {
    "make_env": "envs",
    "make_tasks": "envs",
    "Adapter": "deploy.adapter",
    "Frame": "deploy.adapter",
    "Scene": "deploy.adapter",
    "observe": "deploy.adapter",
    "export_policy": "deploy.export",
    "load_exported": "deploy.exported",
    "load_policy": "deploy.policy",
    "train": "api.train",
    "evaluate": "api.evaluate",
}


def __getattr__(name: str) -> Any:
    import importlib

    if name == "metrics":
        return importlib.import_module("mpcpearl_jax.evaluation.metrics")
    if name in _LAZY:
        return getattr(importlib.import_module(f"mpcpearl_jax.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'mpcpearl_jax' has no attribute {name!r}")
