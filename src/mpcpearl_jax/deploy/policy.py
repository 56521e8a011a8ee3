"""A trained policy outside training: `load_policy(run_dir)` -> `LoadedPolicy`.

`load_policy` reads a run directory's config.json, network.json and policy.msgpack only
(`mpcpearl_jax.runfolder` names them): no environment is built, so a run loads without
its
data file. `LoadedPolicy` acts, infers the latent context z and does both in one call; every
method is pure and jittable. For a robot's own control loop see `mpcpearl_jax.deploy.adapter`, for a
file that needs neither flax nor this package `mpcpearl_jax.deploy.export`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import serialization
from jax import Array

from mpcpearl_jax.config import ExperimentConfig
from mpcpearl_jax.deploy.exported import check_key
from mpcpearl_jax.errors import CheckpointError
from mpcpearl_jax.pearl.networks import Networks
from mpcpearl_jax.runfolder import NETWORK_FILE, POLICY_FILE, load_config, non_finite_leaves


def _is_traced(x: Any) -> bool:
    return isinstance(x, jax.core.Tracer)


def _check_input(name: str, x: Any, expected: str, ok: Callable[[tuple], bool]) -> Array:
    """x as an array; ValueError naming the expected shape if `ok(shape)` fails, or if a concrete
    x holds NaN or inf (traced values, under `jit`, are only shape-checked)."""
    if not _is_traced(x):
        x = jnp.asarray(x)
    if not (jnp.issubdtype(x.dtype, jnp.floating) or jnp.issubdtype(x.dtype, jnp.integer)):
        raise ValueError(f"{name}: expected a numeric array of shape {expected}, got {x.dtype}")
    if not ok(tuple(x.shape)):
        raise ValueError(f"{name}: expected shape {expected}, got {tuple(x.shape)}")
    if not _is_traced(x) and not bool(jnp.all(jnp.isfinite(x))):
        raise ValueError(f"{name}: contains NaN or inf (expected finite values, shape {expected})")
    return x


@dataclass(frozen=True)
class LoadedPolicy:
    """A trained policy rebuilt from a run directory; every method is pure and jittable.

    act(obs [..., O], z [..., L], key=None) -> action [..., 2] in [-1, 1] (deterministic if no key)
    infer_z(context [C, D], mask [C] | None, key=None) -> z [L] (posterior mean if no key)
    __call__(obs, context, key=None, mask=None) -> action: infer z from the context, then act.
    Context rows are (s, a, r, s') with the unscaled reward (D = 2 O + 3): see
    `pearl.context_from`. Inputs are checked: a wrong shape, or NaN / inf in a concrete (not
    traced) input, raises ValueError naming the expected shape. Under `jit` (and in `jit()`) only
    the shapes are checked, at trace time; values are not.
    """

    config: ExperimentConfig
    params: dict
    nets: Networks

    @property
    def obs_dim(self) -> int:
        return self.nets.obs_dim

    @property
    def latent_dim(self) -> int:
        return self.nets.cfg.latent_dim

    def prior_z(self, key: Array | None = None) -> Array:
        """z [L] before any context: the prior's mean, 0 (no key), or a draw from N(0, I)."""
        key, shape = check_key(key), (self.latent_dim,)
        return jnp.zeros(shape) if key is None else jax.random.normal(key, shape)

    @property
    def context_dim(self) -> int:
        return self.nets.context_dim

    def _obs(self, obs: Any) -> Array:
        o = self.obs_dim
        return _check_input("obs", obs, f"[..., {o}]", lambda s: len(s) >= 1 and s[-1] == o)

    def _context(self, context: Any, mask: Any) -> tuple[Array, Array | None]:
        d = self.context_dim
        expected = f"[C, {d}] (C >= 1 rows of (s, a, r, s'), 2 * {self.obs_dim} + 3 columns)"
        context = _check_input(
            "context", context, expected, lambda s: len(s) == 2 and s[0] >= 1 and s[1] == d
        )
        if mask is not None:
            c = context.shape[0]
            mask = jnp.asarray(mask) if not _is_traced(mask) else mask
            if tuple(mask.shape) != (c,):
                raise ValueError(
                    f"mask: expected shape [{c}] (one per context row), got {tuple(mask.shape)}"
                )
        return context, mask

    def infer_z(self, context: Array, mask: Array | None = None, key: Array | None = None):
        key = check_key(key)
        context, mask = self._context(context, mask)
        return self.nets.sample_z(self.params["encoder"], context, key, mask)

    def act(self, obs: Array, z: Array, key: Array | None = None) -> Array:
        obs = self._obs(obs)
        lat = self.latent_dim
        z = _check_input(
            "z", z, f"[..., {lat}] (batch shape of obs)", lambda s: s == obs.shape[:-1] + (lat,)
        )
        return self.nets.act(self.params["policy"], obs, z, check_key(key))

    def __call__(
        self, obs: Array, context: Array, key: Array | None = None, mask: Array | None = None
    ) -> Array:
        obs = self._obs(obs)
        z = self.infer_z(context, mask)
        z = jnp.broadcast_to(z, obs.shape[:-1] + z.shape[-1:])
        return self.act(obs, z, key)

    def jit(self) -> tuple[Callable, Callable]:
        """(jitted act, jitted infer_z): fast paths that check shapes (once, when traced) but
        not values: NaN or inf inputs give NaN actions silently."""
        return jax.jit(self.act), jax.jit(self.infer_z)


def _spec_from_shapes(raw: dict, cfg: ExperimentConfig) -> dict:
    """The `Networks.spec` of a run saved before network.json existed: obs and action dims from
    the shapes of the policy network's first and last layers, the rest from config.json."""
    layers = raw["policy"]["params"]["MLP_0"]
    dense = sorted(layers, key=lambda name: int(name.rsplit("_", 1)[-1]))
    n_in = int(layers[dense[0]]["kernel"].shape[-2])  # obs_dim + latent_dim
    n_out = int(layers[dense[-1]]["kernel"].shape[-1])  # 2 action_dim (mean, log_std)
    return Networks(cfg.pearl, n_in - cfg.pearl.latent_dim, n_out // 2).spec()


def load_policy(path: str | Path, seed_index: int = 0) -> LoadedPolicy:
    """Rebuild the trained policy of seed `seed_index` from a run directory (see module doc)."""
    run_dir = Path(path)
    cfg = load_config(run_dir)
    if not 0 <= seed_index < cfg.seeds:
        raise ValueError(f"seed_index {seed_index} out of range: the run has {cfg.seeds} seed(s)")
    pfile, nfile = run_dir / POLICY_FILE, run_dir / NETWORK_FILE
    if not pfile.is_file():
        raise CheckpointError(f"{pfile}: missing; the run saved no policy yet")
    try:
        raw = serialization.msgpack_restore(pfile.read_bytes())
        spec = json.loads(nfile.read_text()) if nfile.is_file() else _spec_from_shapes(raw, cfg)
        nets = Networks.from_spec(spec, cfg.pearl)
        template = jax.eval_shape(nets.init, jax.random.PRNGKey(0))  # shapes only: no compute
        template = {k: template[k] for k in ("policy", "encoder")}
        stacked = jax.tree_util.tree_map(
            lambda x: jax.ShapeDtypeStruct((cfg.seeds, *x.shape), x.dtype), template
        )
        params = serialization.from_state_dict(stacked, raw)
        shapes = jax.tree_util.tree_map(lambda x: tuple(x.shape), params)
        if shapes != jax.tree_util.tree_map(lambda x: tuple(x.shape), stacked):
            raise ValueError("parameter shapes differ from the saved networks")
    except Exception as e:
        raise CheckpointError(f"{pfile}: corrupt or from a different network size: {e}") from e
    bad = non_finite_leaves(params)
    if bad:
        raise CheckpointError(
            f"{pfile}: non-finite network parameters (NaN or inf in {len(bad)} array(s), e.g. "
            f"{bad[0]}); the run diverged or the file is damaged"
        )
    params = jax.tree_util.tree_map(lambda x: jnp.asarray(x[seed_index]), params)
    return LoadedPolicy(cfg, params, nets)
