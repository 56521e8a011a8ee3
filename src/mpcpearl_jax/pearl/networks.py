"""PEARL networks in flax (method §7): tanh-Gaussian policy, twin Q, V, context encoder.

Initialisation follows the authors' rlkit/PEARL code: hidden weights uniform in +-1/sqrt(fan_in),
hidden biases 0.1, last layer weights and biases uniform in +-3e-3.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, cast

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
from jax import Array

from mpcpearl_jax.envs import observation
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.pearl.config import CROWD_INPUTS, PearlConfig, check_crowd_options

LAST_INIT = 3e-3


def _fanin_init(key: Array, shape: Sequence[int], dtype=jnp.float32) -> Array:
    bound = 1.0 / jnp.sqrt(shape[0])
    return jax.random.uniform(key, shape, dtype, -bound, bound)


def _uniform_init(scale: float):
    def init(key: Array, shape: Sequence[int], dtype=jnp.float32) -> Array:
        return jax.random.uniform(key, shape, dtype, -scale, scale)

    return init


class MLP(nn.Module):
    """ReLU MLP with rlkit initialisation: [..., in] -> [..., out_dim]."""

    hidden: Sequence[int]
    out_dim: int
    layer_norm: bool = False  # extension: LayerNorm before each ReLU (off in the paper)

    @nn.compact
    def __call__(self, x: Array) -> Array:
        for h in self.hidden:
            x = nn.Dense(h, kernel_init=_fanin_init, bias_init=nn.initializers.constant(0.1))(x)
            if self.layer_norm:
                x = nn.LayerNorm()(x)
            x = nn.relu(x)
        return nn.Dense(
            self.out_dim, kernel_init=_uniform_init(LAST_INIT), bias_init=_uniform_init(LAST_INIT)
        )(x)


# the observation's parts as the crowd encoder reads them: the robot's own, one entity per person
# and one per static obstacle (`envs.observation.PARTS`)
ROBOT_PARTS = observation.group("robot")
PEOPLE_PARTS = observation.group("people")
STATIC_PARTS = observation.group("static")


@dataclasses.dataclass(frozen=True)
class CrowdSpec:
    """What shapes a crowd encoder: the observation's parts as (name, start, size), the kind of
    pool ("attention" or "deepsets"), the embedding sizes and how the static obstacles enter
    ("pool": pooled like the people; "flat": their entries as plain features). The number of
    people is the size of `people_present`, the number of static obstacles half the size of
    `static_ego`."""

    layout: tuple[tuple[str, int, int], ...]
    dim: int = 64
    heads: int = 4
    kind: str = "attention"
    static: str = "pool"
    layers: int = 2  # per-entity layers of "deepsets" and "sarl"

    @property
    def parts(self) -> dict[str, tuple[int, int]]:
        return {name: (start, size) for name, start, size in self.layout}

    @property
    def num_people(self) -> int:
        return self.parts.get("people_present", (0, 0))[1]

    @property
    def num_static(self) -> int:
        return self.parts.get("static_ego", (0, 0))[1] // observation.PART["static_ego"].width


class AttentionPool(nn.Module):
    """Entities [..., N, F] (mask [..., N], None = all present) -> one feature [..., dim]: each
    entity embedded with the robot's features [..., R] by one shared MLP, then pooled by
    multi-head attention whose query is the robot's embedding [..., dim]; 0 when no entity is
    present (an absent entity never enters the pool)."""

    dim: int
    heads: int

    @nn.compact
    def __call__(self, ent: Array, mask: Array | None, robot: Array, own: Array) -> Array:
        rob = jnp.broadcast_to(robot[..., None, :], ent.shape[:-1] + robot.shape[-1:])
        e = nn.relu(nn.Dense(self.dim)(jnp.concatenate([ent, rob], axis=-1)))
        e = nn.relu(nn.Dense(self.dim)(e))
        attention = nn.MultiHeadDotProductAttention(
            num_heads=self.heads, qkv_features=self.dim, out_features=self.dim
        )
        att_mask = None if mask is None else mask[..., None, None, :]  # [..., heads, q, N]
        out = attention(own[..., None, :], e, e, mask=att_mask)[..., 0, :]
        if mask is not None:
            out = jnp.where(jnp.any(mask, axis=-1, keepdims=True), out, 0.0)
        return out


def _embed_entities(ent: Array, robot: Array, dim: int, layers: int) -> Array:
    """Entities [..., N, F] with the robot's features [..., R] -> [..., N, dim] by one shared
    ReLU MLP of `layers` layers (`pearl.crowd_layers`), its first layer's robot term computed
    once per observation (the same affine map of [entity, robot]). Called inside a pool's
    compact `__call__`, whose parameters ("entity", "robot", "Dense_k") these layers are."""
    h = nn.Dense(dim, name="entity")(ent)
    h = h + nn.Dense(dim, use_bias=False, name="robot")(robot)[..., None, :]
    e = nn.relu(h)
    for _ in range(layers - 1):
        e = nn.relu(nn.Dense(dim)(e))
    return e


class DeepSetPool(nn.Module):
    """Entities [..., N, F] (mask [..., N], None = all present) -> [..., 2 dim]: each entity
    embedded with the robot's features [..., R] by one shared 2-layer ReLU MLP, then the masked
    mean and the masked max over the present entities (Deep Sets, Zaheer et al. 2017; the mean
    and max pools of crowd-navigation encoders). The first layer's robot term is computed once
    per observation, not once per entity (the same affine map of [entity, robot]). 0 when no
    entity is present: the embeddings are non-negative, so 0 is the max's neutral element."""

    dim: int
    layers: int = 2  # per-entity layers (`pearl.crowd_layers`)

    @nn.compact
    def __call__(self, ent: Array, mask: Array | None, robot: Array, own: Array) -> Array:
        del own
        e = _embed_entities(ent, robot, self.dim, self.layers)
        if mask is None:
            return jnp.concatenate([jnp.mean(e, axis=-2), jnp.max(e, axis=-2)], axis=-1)
        m = mask[..., None].astype(e.dtype)
        count = jnp.maximum(jnp.sum(m, axis=-2), 1.0)
        mean = jnp.sum(e * m, axis=-2) / count
        top = jnp.max(e * m, axis=-2)
        return jnp.concatenate([mean, top], axis=-1)


class ScorePool(nn.Module):
    """Entities [..., N, F] (mask [..., N], None = all present) -> [..., 2 dim]: each entity
    embedded with the robot's features as in `DeepSetPool`, then pooled by a softmax over one
    learned scalar score per entity (SARL's attention, Chen et al. 2019: the embedding already
    holds the robot's state, so the score weighs each person by her relation to the robot),
    beside the masked max. Absent entities get no weight; 0 when no entity is present."""

    dim: int
    layers: int = 2  # per-entity layers (`pearl.crowd_layers`)

    @nn.compact
    def __call__(self, ent: Array, mask: Array | None, robot: Array, own: Array) -> Array:
        del own
        e = _embed_entities(ent, robot, self.dim, self.layers)
        score = nn.Dense(1, name="score")(e)[..., 0]  # [..., N]
        if mask is None:
            w = jax.nn.softmax(score, axis=-1)
            return jnp.concatenate([jnp.sum(w[..., None] * e, -2), jnp.max(e, -2)], axis=-1)
        w = jax.nn.softmax(jnp.where(mask, score, -1e9), axis=-1) * mask
        m = mask[..., None].astype(e.dtype)
        return jnp.concatenate([jnp.sum(w[..., None] * e, -2), jnp.max(e * m, -2)], axis=-1)


class CrowdEncoder(nn.Module):
    """Flat observation [..., O] -> features [...,F]: the robot's own features (pose, goal,
    time), the people pooled and the static obstacles pooled or as plain features
    (`pearl.crowd_encoder`: "attention", SARL, Chen et al. 2019, with HEIGHT's two entity kinds;
    "deepsets", mean and max pools; "sarl", a scalar score per person and a softmax, with the
    max). Each person's entries (arena and egocentric position,
    displacement, forecast, presence) form one entity; the people's presence entry is the mask.
    Invariant to the order of the people."""

    spec: CrowdSpec

    @nn.compact
    def __call__(self, obs: Array) -> Array:
        batch = obs.shape[:-1]
        parts = {n: obs[..., s : s + k] for n, (s, k) in self.spec.parts.items()}
        robot = jnp.concatenate([parts[n] for n in ROBOT_PARTS if n in parts], axis=-1)
        attention = self.spec.kind == "attention"
        own = nn.relu(nn.Dense(self.spec.dim, name="robot")(robot)) if attention else robot
        feats = [robot]

        def entities(names: Sequence[str], n: int) -> Array:
            # explicit sizes: a batch of 0 observations has no -1 to infer
            return jnp.concatenate(
                [parts[x].reshape(*batch, n, parts[x].shape[-1] // n) for x in names if x in parts],
                axis=-1,
            )

        def pool(name: str) -> nn.Module:
            if attention:
                return AttentionPool(self.spec.dim, self.spec.heads, name=name)
            if self.spec.kind == "sarl":
                return ScorePool(self.spec.dim, self.spec.layers, name=name)
            return DeepSetPool(self.spec.dim, self.spec.layers, name=name)

        h, s = self.spec.num_people, self.spec.num_static
        if h > 0:
            present = parts["people_present"] > 0
            feats.append(pool("people")(entities(PEOPLE_PARTS, h), present, robot, own))
        if s > 0 and self.spec.static == "pool":
            feats.append(pool("static")(entities(STATIC_PARTS, s), None, robot, own))
        elif s > 0:
            feats.extend(parts[n] for n in STATIC_PARTS if n in parts)
        return jnp.concatenate(feats, axis=-1)


def _see(crowd: CrowdSpec | None, obs: Array, name: str | None = None) -> Array:
    """The observation as the network sees it: through a crowd encoder of its own, or as is."""
    return obs if crowd is None else CrowdEncoder(crowd, name=name)(obs)


class TwinQ(nn.Module):
    """Two Q heads Q_i(s, a, z): returns ([...], [...])."""

    hidden: Sequence[int]
    layer_norm: bool = False
    crowd: CrowdSpec | None = None
    # one crowd encoder ("crowd") read by both heads (`pearl.crowd_shared`), else one per head
    shared: bool = False

    @nn.compact
    def __call__(self, obs: Array, action: Array, z: Array) -> tuple[Array, Array]:
        seen = _see(self.crowd, obs, "crowd") if self.shared else None

        def head(name: str) -> Array:
            x = seen if seen is not None else _see(self.crowd, obs, f"{name}_crowd")
            x = jnp.concatenate([x, action, z], axis=-1)
            return MLP(self.hidden, 1, self.layer_norm, name=name)(x)[..., 0]

        return head("q1"), head("q2")


class ValueNet(nn.Module):
    hidden: Sequence[int]
    layer_norm: bool = False
    crowd: CrowdSpec | None = None

    @nn.compact
    def __call__(self, obs: Array, z: Array) -> Array:
        x = jnp.concatenate([_see(self.crowd, obs, "crowd"), z], axis=-1)
        return MLP(self.hidden, 1, self.layer_norm)(x)[..., 0]


class PolicyNet(nn.Module):
    """Outputs (mean, log_std) [..., A] of the pre-tanh Gaussian, log_std clamped (method §7)."""

    hidden: Sequence[int]
    action_dim: int
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    crowd: CrowdSpec | None = None

    @nn.compact
    def __call__(self, obs: Array, z: Array) -> tuple[Array, Array]:
        x = jnp.concatenate([_see(self.crowd, obs, "crowd"), z], axis=-1)
        out = MLP(self.hidden, 2 * self.action_dim)(x)
        mean, log_std = jnp.split(out, 2, axis=-1)
        return mean, jnp.clip(log_std, self.log_std_min, self.log_std_max)


class ContextEncoder(nn.Module):
    """Per-transition Gaussian factors: context [..., C, D] -> (mean, var) [..., C, latent]."""

    hidden: Sequence[int]
    latent_dim: int
    min_var: float = 1e-7

    @nn.compact
    def __call__(self, context: Array) -> tuple[Array, Array]:
        out = MLP(self.hidden, 2 * self.latent_dim)(context)
        mean, pre_var = jnp.split(out, 2, axis=-1)
        return mean, jnp.maximum(jax.nn.softplus(pre_var), self.min_var)


def tanh_gaussian(mean: Array, log_std: Array) -> distrax.Distribution:
    """Tanh-squashed diagonal Gaussian; log-probs come from the pre-tanh sample (no atanh)."""
    base = distrax.MultivariateNormalDiag(mean, jnp.exp(log_std))
    return distrax.Transformed(base, distrax.Block(distrax.Tanh(), ndims=1))


def product_of_gaussians(mean: Array, var: Array, mask: Array | None = None) -> tuple[Array, Array]:
    """Posterior q(z | c) proportional to prod_n N(mean_n, var_n) (PEARL eq. for q_phi).

    Args:
      mean, var: [..., C, L] per-transition factors; mask: [..., C] (1 = use the transition).
    Returns:
      (mean, var) [..., L]. Callers pass at least one valid transition (with none, use the
      prior N(0, I) directly).
    """
    precision = 1.0 / var
    if mask is not None:
        precision = precision * mask[..., None]
    post_var = 1.0 / jnp.maximum(jnp.sum(precision, axis=-2), 1e-12)
    post_mean = post_var * jnp.sum(mean * precision, axis=-2)
    return post_mean, post_var


def kl_to_standard_normal(mean: Array, var: Array) -> Array:
    """KL(N(mean, diag var) || N(0, I)) summed over the last axis: [..., L] -> [...]."""
    return 0.5 * jnp.sum(var + mean**2 - 1.0 - jnp.log(var), axis=-1)


# the PearlConfig fields that shape the networks (saved with a policy, see `Networks.spec`)
NETWORK_FIELDS = (
    "latent_dim",
    "hidden",
    "encoder_hidden",
    "layer_norm",
    "log_std_min",
    "log_std_max",
    "min_posterior_var",
    "use_context",
)
# the fields of the crowd encoder, saved only when it is on (a spec without them has none)
CROWD_FIELDS = (
    "crowd_encoder",
    "crowd_dim",
    "crowd_heads",
    "crowd_static",
    "crowd_shared",
    "crowd_layers",
)


def check_crowd_inputs(cfg: PearlConfig, part_names: Sequence[str]) -> None:
    """ConfigError naming the env options a crowd encoder needs when the observation's parts
    `part_names` lack them (nothing to check without one)."""
    check_crowd_options(cfg, observation.missing_options(part_names, CROWD_INPUTS))


def crowd_spec(
    cfg: PearlConfig, obs_dim: int, obs_layout: Sequence[dict] | None
) -> CrowdSpec | None:
    """The crowd encoder's spec under `cfg` (None for `crowd_encoder` "none"); ConfigError
    naming the missing observation entries when the layout lacks them."""
    if cfg.crowd_encoder == "none":
        return None
    if obs_layout is None:
        raise ConfigError(
            f"pearl.crowd_encoder={cfg.crowd_encoder} needs the observation's layout "
            "(Networks(..., obs_layout=env.obs_layout(tasks)))"
        )
    layout = tuple((str(p["name"]), int(p["start"]), int(p["size"])) for p in obs_layout)
    check_crowd_inputs(cfg, [n for n, _, _ in layout])
    end = max(s + k for _, s, k in layout)
    if end != obs_dim:
        raise ConfigError(f"observation layout covers {end} entries, the observation has {obs_dim}")
    return CrowdSpec(
        layout,
        cfg.crowd_dim,
        cfg.crowd_heads,
        cfg.crowd_encoder,
        cfg.crowd_static,
        cfg.crowd_layers,
    )


class Networks:
    """The flax modules of one PEARL agent, built from a config."""

    def __init__(
        self,
        cfg: PearlConfig,
        obs_dim: int,
        action_dim: int,
        obs_layout: Sequence[dict] | None = None,
    ):
        """`obs_layout`: the observation's parts (`NavEnv.obs_layout`), needed by a crowd
        encoder (`pearl.crowd_encoder`), ignored without one."""
        self.cfg = cfg
        self.obs_dim = int(obs_dim)
        self.action_dim = int(action_dim)
        self.context_dim = 2 * obs_dim + action_dim + 1
        self.crowd = crowd_spec(cfg, self.obs_dim, obs_layout)
        self.policy = PolicyNet(
            cfg.hidden, action_dim, cfg.log_std_min, cfg.log_std_max, crowd=self.crowd
        )
        # `pearl.crowd_shared`: the critics' one encoder, read by the policy and V as features
        self.shared = self.crowd is not None and cfg.crowd_shared
        self.q = TwinQ(cfg.hidden, cfg.layer_norm, crowd=self.crowd, shared=self.shared)
        self.v = ValueNet(cfg.hidden, cfg.layer_norm, crowd=self.crowd)
        self.encoder = ContextEncoder(cfg.encoder_hidden, cfg.latent_dim, cfg.min_posterior_var)

    def spec(self) -> dict[str, Any]:
        """Everything that shapes the networks, as JSON-ready values (saved beside a policy as
        network.json, as brax saves its network config): `from_spec` rebuilds them from it
        alone, without the environment."""
        out: dict[str, Any] = {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "context_dim": self.context_dim,
        }
        for f in NETWORK_FIELDS:
            v = getattr(self.cfg, f)
            out[f] = list(v) if isinstance(v, tuple) else v
        if self.crowd is not None:
            out.update({f: getattr(self.cfg, f) for f in CROWD_FIELDS})
            out["obs_layout"] = [
                {"name": n, "start": s, "size": k} for n, s, k in self.crowd.layout
            ]
        return out

    @classmethod
    def from_spec(cls, spec: dict[str, Any], cfg: PearlConfig | None = None) -> Networks:
        """The networks of `spec` (see `spec`); the other PearlConfig fields (losses, schedule)
        come from `cfg` (default: PearlConfig()). Other entries are ignored (a run trained with
        the removed CrossQ critics names `crossq` there; its policy and encoder are these).
        ValueError if the spec is incomplete or its context_dim does not match its obs and
        action dims."""
        missing = [f for f in ("obs_dim", "action_dim", *NETWORK_FIELDS) if f not in spec]
        if missing:
            raise ValueError(f"network spec lacks {missing}")
        fields = {
            f: tuple(spec[f]) if isinstance(spec[f], list) else spec[f] for f in NETWORK_FIELDS
        }
        fields.update({f: spec[f] for f in CROWD_FIELDS if f in spec})
        fields.setdefault("crowd_encoder", "none")
        nets = cls(
            (cfg or PearlConfig()).replace(**fields),
            spec["obs_dim"],
            spec["action_dim"],
            spec.get("obs_layout"),
        )
        if "context_dim" in spec and spec["context_dim"] != nets.context_dim:
            raise ValueError(
                f"network spec: context_dim {spec['context_dim']} != 2 obs_dim + action_dim + 1 "
                f"= {nets.context_dim}"
            )
        return nets

    def init(self, key: Array) -> dict:
        """Parameters {policy, q, v, encoder} for a fresh agent."""
        k_pi, k_q, k_v, k_e = jax.random.split(key, 4)
        obs = jnp.zeros((1, self.obs_dim))
        act = jnp.zeros((1, self.action_dim))
        z = jnp.zeros((1, self.cfg.latent_dim))
        ctx = jnp.zeros((1, 1, self.context_dim))
        params = {
            "policy": self.policy.init(k_pi, obs, z),
            "q": self.q.init(k_q, obs, act, z),
            "v": self.v.init(k_v, obs, z),
            "encoder": self.encoder.init(k_e, ctx),
        }
        return self.share_crowd(params) if self.shared else params

    # ---- the shared crowd encoder (`pearl.crowd_shared`): the critics own it; the policy and
    # V hold copies of it (so each still acts from the observation alone) and read its features
    # with stopped gradients
    def share_crowd(self, params: dict) -> dict:
        """`params` with the policy's and V's crowd encoders set to the critics' (copies)."""
        crowd = params["q"]["params"]["crowd"]
        out = dict(params)
        for name in ("policy", "v"):
            inner = dict(out[name]["params"])
            inner["crowd"] = jax.tree_util.tree_map(jnp.copy, crowd)
            out[name] = {**out[name], "params": inner}
        return out

    def encode(self, params: Any, obs: Array) -> Array:
        """The crowd encoder's features [..., F] of obs [..., O] under the encoder in `params`
        (a policy's, critics' or V's parameters)."""
        assert self.crowd is not None
        enc = CrowdEncoder(self.crowd)
        return cast(Array, enc.apply({"params": params["params"]["crowd"]}, obs))

    def policy_head(self, params: Any, feats: Array, z: Array) -> tuple[Array, Array]:
        """`policy_out` on features [..., F] (`encode`): policy_out(p, o, z) = policy_head(p,
        encode(p, o), z)."""
        mlp = MLP(self.cfg.hidden, 2 * self.action_dim)
        out = mlp.apply({"params": params["params"]["MLP_0"]}, jnp.concatenate([feats, z], -1))
        mean, log_std = jnp.split(cast(Array, out), 2, axis=-1)
        return mean, jnp.clip(log_std, self.cfg.log_std_min, self.cfg.log_std_max)

    def q_heads(self, params: Any, feats: Array, action: Array, z: Array) -> tuple[Array, Array]:
        """`q_values` of the shared-encoder critics on features [..., F]."""
        x = jnp.concatenate([feats, action, z], axis=-1)

        def head(name: str) -> Array:
            mlp = MLP(self.cfg.hidden, 1, self.cfg.layer_norm)
            return cast(Array, mlp.apply({"params": params["params"][name]}, x))[..., 0]

        return head("q1"), head("q2")

    def value_head(self, params: Any, feats: Array, z: Array) -> Array:
        """`value` on features [..., F]."""
        mlp = MLP(self.cfg.hidden, 1, self.cfg.layer_norm)
        x = jnp.concatenate([feats, z], axis=-1)
        return cast(Array, mlp.apply({"params": params["params"]["MLP_0"]}, x))[..., 0]

    # typed applies: flax's `apply` is untyped
    def policy_out(self, params: Any, obs: Array, z: Array) -> tuple[Array, Array]:
        """(mean, log_std) [..., A] of the pre-tanh Gaussian."""
        return cast(tuple[Array, Array], self.policy.apply(params, obs, z))

    def q_values(self, params: Any, obs: Array, action: Array, z: Array) -> tuple[Array, Array]:
        return cast(tuple[Array, Array], self.q.apply(params, obs, action, z))

    def value(self, params: Any, obs: Array, z: Array) -> Array:
        return cast(Array, self.v.apply(params, obs, z))

    def factors(self, params: Any, context: Array) -> tuple[Array, Array]:
        """Per-transition (mean, var) [..., C, L]."""
        return cast(tuple[Array, Array], self.encoder.apply(params, context))

    def posterior(self, enc_params: Any, context: Array, mask: Array | None = None):
        """(mean, var) [..., L] of q(z | context [..., C, D])."""
        mean, var = self.factors(enc_params, context)
        return product_of_gaussians(mean, var, mask)

    def posterior_sample(
        self,
        enc_params: Any,
        context: Array,
        key: Array | None = None,
        mask: Array | None = None,
    ) -> tuple[Array, Array, Array]:
        """The one sampler of z ~ q(z | c) (PEARL eq. for q_phi): (z, mean, var) [..., L].

        context [..., C, D]; mask [..., C] (1 = use the row): where it selects no row, q is the
        prior N(0, I). z = mean + sqrt(var) * noise (reparameterised), the posterior mean when
        key is None. Without an encoder (`use_context` false, plain SAC) z = 0 and (mean, var) =
        (0, 1), so the KL term vanishes.
        """
        shape = context.shape[:-2] + (self.cfg.latent_dim,)
        if not self.cfg.use_context:
            return jnp.zeros(shape), jnp.zeros(shape), jnp.ones(shape)
        mean, var = self.posterior(enc_params, context, mask)
        if mask is not None:
            has = jnp.any(mask > 0, axis=-1, keepdims=True)
            mean, var = jnp.where(has, mean, 0.0), jnp.where(has, var, 1.0)
        if key is None:
            return mean, mean, var
        return mean + jnp.sqrt(var) * jax.random.normal(key, mean.shape), mean, var

    def sample_z(
        self,
        enc_params: Any,
        context: Array,
        key: Array | None = None,
        mask: Array | None = None,
    ) -> Array:
        """z [..., L] ~ q(z | context [..., C, D]): see `posterior_sample`."""
        return self.posterior_sample(enc_params, context, key, mask)[0]

    def prior_z(self, key: Array, shape: tuple[int, ...]) -> Array:
        """z [*shape, L] from the prior N(0, I), the one draw before any context (PEARL's
        exploration episodes); 0 without an encoder (`use_context` false), as `posterior_sample`
        gives."""
        shape = (*shape, self.cfg.latent_dim)
        return jax.random.normal(key, shape) if self.cfg.use_context else jnp.zeros(shape)

    def act(self, policy_params: Any, obs: Array, z: Array, key: Array | None) -> Array:
        """Normalized action [..., A]: a tanh-Gaussian sample, or tanh(mean) when key is None."""
        mean, log_std = self.policy_out(policy_params, obs, z)
        if key is None:
            return jnp.tanh(mean)
        return tanh_gaussian(mean, log_std).sample(seed=key)
