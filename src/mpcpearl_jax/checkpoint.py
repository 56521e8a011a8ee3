"""Checkpoints (orbax) of the full training state, and `load_policy` for use outside training.

A run directory holds:
  config.json         the ExperimentConfig (what `load_policy` and `--resume` rebuild from)
  checkpoints/<it>/   orbax checkpoints of the whole TrainState (last few kept)
  policy.msgpack      policy + encoder parameters of every seed (flax serialization)
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp
from flax import serialization
from jax import Array

from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.envs import make_env, make_tasks
from mpcpearl_jax.pearl.networks import Networks


class CheckpointError(RuntimeError):
    """A checkpoint is missing, corrupt, or does not match the configuration."""


CONFIG_FILE = "config.json"
POLICY_FILE = "policy.msgpack"


def save_config(run_dir: Path, cfg: ExperimentConfig) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / CONFIG_FILE).write_text(cfg.to_json())


def load_config(run_dir: str | Path) -> ExperimentConfig:
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise CheckpointError(f"{path}: no config.json; is this a run directory?")
    try:
        return ExperimentConfig.from_dict(json.loads(path.read_text()))
    except (json.JSONDecodeError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: unreadable or invalid config ({e})") from e


def check_resumable(saved: ExperimentConfig, cfg: ExperimentConfig, run_dir: Path) -> None:
    """Resuming needs the same config except for the number of iterations."""
    da, db = saved.to_dict(), cfg.to_dict()
    da["train"].pop("iterations")
    db["train"].pop("iterations")
    diff = _diff(json.loads(json.dumps(da)), json.loads(json.dumps(db)))
    if diff:
        raise CheckpointError(
            f"{run_dir}: the saved config differs from the requested one in {diff}; "
            "resume with the same settings (only --iterations may change) or use a new --out"
        )


def _diff(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    return [prefix.rstrip(".")] if a != b else []


class Checkpointer:
    """Saves and restores the whole TrainState under run_dir/checkpoints."""

    def __init__(self, run_dir: str | Path, keep: int = 3):
        self.run_dir = Path(run_dir).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True)
        self.manager = ocp.CheckpointManager(self.run_dir / "checkpoints", options=options)

    def latest(self) -> int | None:
        return self.manager.latest_step()

    def save(self, step: int, state, policy_params: dict) -> None:
        self.manager.save(step, args=ocp.args.StandardSave(state))
        self.manager.wait_until_finished()
        (self.run_dir / POLICY_FILE).write_bytes(serialization.to_bytes(policy_params))

    def restore(self, template, step: int | None = None):
        step = self.latest() if step is None else step
        if step is None:
            raise CheckpointError(f"{self.run_dir}: no checkpoint to resume from")
        abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, template)
        try:
            return self.manager.restore(step, args=ocp.args.StandardRestore(abstract))
        except Exception as e:  # orbax raises many types for corrupt or mismatched trees
            raise CheckpointError(
                f"{self.run_dir}/checkpoints/{step}: cannot restore the training state "
                f"(corrupt, or saved with a different configuration): {type(e).__name__}: {e}"
            ) from e

    def close(self) -> None:
        self.manager.close()


@dataclass(frozen=True)
class LoadedPolicy:
    """A trained policy rebuilt from a run directory; every method is pure and jittable.

    act(obs [..., O], z [..., L], key=None) -> action [..., 2] in [-1, 1] (deterministic if no key)
    infer_z(context [C, D], mask [C] | None, key=None) -> z [L] (posterior mean if no key)
    __call__(obs, context, key=None, mask=None) -> action: infer z from the context, then act.
    Context rows are (s, a, r, s') with the unscaled reward: see `pearl.context_from`.
    """

    config: ExperimentConfig
    params: dict
    nets: Networks
    env_config: Any

    @property
    def obs_dim(self) -> int:
        return self.nets.obs_dim

    @property
    def latent_dim(self) -> int:
        return self.nets.cfg.latent_dim

    def prior_z(self, key: Array | None = None) -> Array:
        shape = (self.latent_dim,)
        return jnp.zeros(shape) if key is None else jax.random.normal(key, shape)

    def infer_z(self, context: Array, mask: Array | None = None, key: Array | None = None):
        if not self.nets.cfg.use_context:
            return jnp.zeros((self.latent_dim,))
        mean, var = self.nets.posterior(self.params["encoder"], context, mask)
        return mean if key is None else mean + jnp.sqrt(var) * jax.random.normal(key, mean.shape)

    def act(self, obs: Array, z: Array, key: Array | None = None) -> Array:
        return self.nets.act(self.params["policy"], obs, z, key)

    def __call__(
        self, obs: Array, context: Array, key: Array | None = None, mask: Array | None = None
    ) -> Array:
        z = self.infer_z(context, mask)
        z = jnp.broadcast_to(z, obs.shape[:-1] + z.shape[-1:])
        return self.act(obs, z, key)

    def jit(self) -> tuple[Callable, Callable]:
        """(jitted act, jitted infer_z)."""
        return jax.jit(self.act), jax.jit(self.infer_z)


def load_policy(
    path: str | Path, seed_index: int = 0, data: str | Path | None = None
) -> LoadedPolicy:
    """Rebuild the trained policy of seed `seed_index` from a run directory (see module doc).

    data: the run's trajectory file (sidewalk) where the path in config.json is not valid here."""
    run_dir = Path(path)
    cfg = load_config(run_dir)
    if data is not None:
        cfg = cfg.replace(data=str(data))
    if not 0 <= seed_index < cfg.seeds:
        raise ValueError(f"seed_index {seed_index} out of range: the run has {cfg.seeds} seed(s)")
    env = make_env(cfg.env, **cfg.env_overrides)
    kw = {"data": cfg.data} if cfg.data else {}
    tasks = make_tasks(cfg.env, "test", cfg.task_seed, config=env.config, **kw)
    obs_dim = env.obs_dim(tasks)
    nets = Networks(cfg.pearl, obs_dim, env.action_dim)
    template = nets.init(jax.random.PRNGKey(0))
    template = {k: template[k] for k in ("policy", "encoder")}
    stacked = jax.tree_util.tree_map(lambda x: jnp.stack([x] * cfg.seeds), template)
    pfile = run_dir / POLICY_FILE
    if not pfile.is_file():
        raise CheckpointError(f"{pfile}: missing; the run saved no policy yet")
    try:
        params = serialization.from_bytes(stacked, pfile.read_bytes())
    except Exception as e:
        raise CheckpointError(f"{pfile}: corrupt or from a different network size: {e}") from e
    params = jax.tree_util.tree_map(lambda x: jnp.asarray(x[seed_index]), params)
    return LoadedPolicy(cfg, params, nets, env.config)
