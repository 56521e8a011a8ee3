"""GrBAL's learned dynamics model and its meta-training step (Nagabandi et al., ICLR 2019).

The model f_theta(o, a) predicts the change of the *dynamic* part of the observation over one
step: the robot pose (x, y, theta) and the people's positions (and their last-step displacement
when `env.observe_velocity` is on); the static part (table centres) is copied. It is a ReLU MLP
(`pearl.networks.MLP`) on normalized inputs (the heading enters as sin / cos) with normalized
targets; the normalization statistics are recomputed from the buffers before every fit, as in the
GrBAL authors' code.

Meta-training (GrBAL): a window of M past and K future consecutive transitions of one episode;
theta' = theta - alpha grad L_past(theta) (one SGD step), and the outer loss is L_future(theta'),
minimised by Adam with the gradient taken *through* the inner step (second order), all windows
vmapped in one jitted step.

The inner gradient of a dense layer over M samples is a sum of M outer products,
grad W = H' D (H [M, in] the layer inputs, D [M, out] the loss gradients at its outputs), so the
adapted layer applied to a row h is h W - alpha (h H') D: the meta-loss never forms the adapted
weights of each window (256 windows x 3 x 256 units would be 36M numbers per step), only the
factors H and D, and is exactly the loss of the adapted parameters (`adapt`, tested equal).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax import Array

from mpcpearl_jax.pearl.networks import MLP
from mpcpearl_jax.pearl.types import Transitions

Params = dict


class ObsLayout(NamedTuple):
    """Where things sit in an observation (see `envs.navigation.NavEnv.observe`).

    [x, y, theta / pi | people 2H | people's displacement 2V | static centres 2S], all in [-1, 1];
    the first `dyn_dim` entries change within an episode, the static ones do not.
    """

    num_humans: int
    num_velocity: int  # H with env.observe_velocity, else 0
    num_static: int  # S with env.observe_static, else 0

    @property
    def dyn_dim(self) -> int:
        return 3 + 2 * self.num_humans + 2 * self.num_velocity

    @property
    def obs_dim(self) -> int:
        return self.dyn_dim + 2 * self.num_static

    @property
    def feature_dim(self) -> int:
        """Model input: the observation with theta as (sin, cos), and the 2-d action."""
        return self.obs_dim + 1 + 2


def layout_of(env, tasks) -> ObsLayout:
    """The observation layout of `env` (a NavEnv) on its tasks (stacked or single)."""
    cfg = env.config
    unsupported = {
        "observe_relative": cfg.observe_relative,
        "sensing_radius": cfg.sensing_radius > 0,
        "observe_time": cfg.observe_time,
        "observe_sorted": cfg.observe_sorted,
    }
    for field, on in unsupported.items():
        if on:
            from mpcpearl_jax.errors import ConfigError

            raise ConfigError(
                f"env.{field}: not supported by GrBAL (its learned model and planner use the "
                "paper's observation and reward)"
            )
    h = int(tasks.human_pos.shape[-2])
    s = int(tasks.static_lo.shape[-2]) if cfg.observe_static else 0
    return ObsLayout(h, h if cfg.observe_velocity else 0, s)


def wrap_unit(x: Array) -> Array:
    """Wrap a heading in units of pi (theta / pi) to [-1, 1)."""
    return jnp.mod(x + 1.0, 2.0) - 1.0


def features(obs: Array, action: Array) -> Array:
    """Model input [..., O + 3]: obs with theta / pi replaced by (sin theta, cos theta), action."""
    th = jnp.pi * obs[..., 2:3]
    return jnp.concatenate([obs[..., :2], jnp.sin(th), jnp.cos(th), obs[..., 3:], action], axis=-1)


def targets(obs: Array, next_obs: Array, layout: ObsLayout) -> Array:
    """Change of the dynamic part [..., D]; the heading change wrapped to [-1, 1)."""
    d = next_obs[..., : layout.dyn_dim] - obs[..., : layout.dyn_dim]
    return d.at[..., 2].set(wrap_unit(d[..., 2]))


class Normalizer(struct.PyTreeNode):
    """Mean / std of the model inputs [F] and targets [D]."""

    in_mean: Array
    in_std: Array
    out_mean: Array
    out_std: Array


def identity_normalizer(layout: ObsLayout) -> Normalizer:
    f, d = layout.feature_dim, layout.dyn_dim
    return Normalizer(jnp.zeros(f), jnp.ones(f), jnp.zeros(d), jnp.ones(d))


def fit_normalizer(data: Transitions, valid: Array, layout: ObsLayout) -> Normalizer:
    """Statistics of the valid rows (mask `valid`, same leading shape as the data)."""
    x = features(data.obs, data.action)
    y = targets(data.obs, data.next_obs, layout)
    w = valid.astype(jnp.float32)[..., None]
    count = jnp.maximum(jnp.sum(w), 1.0)
    axes = tuple(range(x.ndim - 1))

    def stats(v):
        mean = jnp.sum(v * w, axis=axes) / count
        var = jnp.sum(w * (v - mean) ** 2, axis=axes) / count
        return mean, jnp.sqrt(var) + 1e-6

    im, istd = stats(x)
    om, ostd = stats(y)
    return Normalizer(im, istd, om, ostd)


def mlp_forward(
    params: Params, x: Array, eps: list[Array] | None = None
) -> tuple[Array, list[Array]]:
    """The flax `MLP` (Dense_0 .. Dense_L, ReLU between) applied to x [..., in] by hand.

    eps: optional additive perturbations of every layer's output (pre-activation); the gradient
    of a loss with respect to them is the D of the module doc. Returns (output, the inputs of
    every layer)."""
    n = len(params)
    h, inputs = x, []
    for i in range(n):
        layer = params[f"Dense_{i}"]
        inputs.append(h)
        z = h @ layer["kernel"] + layer["bias"]
        if eps is not None:
            z = z + eps[i]
        h = jax.nn.relu(z) if i < n - 1 else z
    return h, inputs


class InnerStep(NamedTuple):
    """One inner SGD step in factored form: per layer the inputs H [M, in] and the gradients
    D [M, out] at the outputs of the M adaptation samples, and the step size."""

    inputs: list[Array]
    grads: list[Array]
    lr: float


def adapted_forward(params: Params, step: InnerStep, x: Array) -> Array:
    """The MLP with theta' = theta - lr grad applied to x [..., in], from the factors alone:
    z = h W + b - lr ((h H') D + sum_m D_m)."""
    n = len(params)
    h = x
    for i in range(n):
        layer = params[f"Dense_{i}"]
        hh, dd = step.inputs[i], step.grads[i]
        z = h @ layer["kernel"] + layer["bias"]
        z = z - step.lr * ((h @ hh.T) @ dd + jnp.sum(dd, axis=0))
        h = jax.nn.relu(z) if i < n - 1 else z
    return h


class DynamicsModel:
    """f_theta on observations of `layout`; every method is pure (vmap / jit freely)."""

    def __init__(self, layout: ObsLayout, hidden: tuple[int, ...]):
        self.layout = layout
        self.net = MLP(tuple(hidden), layout.dyn_dim)

    def init(self, key: Array) -> Params:
        return self.net.init(key, jnp.zeros((1, self.layout.feature_dim)))["params"]

    def inputs(self, norm: Normalizer, obs: Array, action: Array) -> Array:
        return (features(obs, action) - norm.in_mean) / norm.in_std

    def scaled_targets(self, norm: Normalizer, obs: Array, next_obs: Array) -> Array:
        return (targets(obs, next_obs, self.layout) - norm.out_mean) / norm.out_std

    def delta_normalized(self, params: Params, norm: Normalizer, obs: Array, action: Array):
        """Predicted normalized change [..., D]."""
        return mlp_forward(params, self.inputs(norm, obs, action))[0]

    def predict(self, params: Params, norm: Normalizer, obs: Array, action: Array) -> Array:
        """Predicted next observation [..., O]: dynamic part changed, heading wrapped, entries
        clipped to the observation box [-1, 1], static part copied."""
        dyn = self.layout.dyn_dim
        d = self.delta_normalized(params, norm, obs, action) * norm.out_std + norm.out_mean
        nxt = obs[..., :dyn] + d
        nxt = jnp.clip(nxt.at[..., 2].set(wrap_unit(nxt[..., 2])), -1.0, 1.0)
        return jnp.concatenate([nxt, obs[..., dyn:]], axis=-1)

    def loss(
        self,
        params: Params,
        norm: Normalizer,
        obs: Array,
        action: Array,
        next_obs: Array,
        mask: Array | None = None,
    ) -> Array:
        """Mean squared error of the normalized change over the rows where mask is 1 (all rows
        if None); 0 when no row is valid."""
        pred = self.delta_normalized(params, norm, obs, action)
        return _mse(pred, self.scaled_targets(norm, obs, next_obs), mask)

    def adapt(
        self,
        params: Params,
        norm: Normalizer,
        obs: Array,
        action: Array,
        next_obs: Array,
        inner_lr: float,
        mask: Array | None = None,
    ) -> Params:
        """GrBAL's inner step: theta - inner_lr * grad of the loss on the given transitions."""
        g = jax.grad(self.loss)(params, norm, obs, action, next_obs, mask)
        return jax.tree_util.tree_map(lambda p, gi: p - inner_lr * gi, params, g)

    def inner_step(
        self,
        params: Params,
        norm: Normalizer,
        obs: Array,
        action: Array,
        next_obs: Array,
        inner_lr: float,
        mask: Array | None = None,
    ) -> InnerStep:
        """`adapt` in factored form (for `adapted_forward`); rows [M, ...]."""
        x = self.inputs(norm, obs, action)
        y = self.scaled_targets(norm, obs, next_obs)
        out, inputs = mlp_forward(params, x)
        eps0 = [jnp.zeros(x.shape[:-1] + (layer["bias"].shape[-1],)) for layer in _ordered(params)]
        grads = jax.grad(lambda e: _mse(mlp_forward(params, x, e)[0], y, mask))(eps0)
        return InnerStep(inputs, grads, inner_lr)

    def adapted_loss(
        self, params: Params, step: InnerStep, norm: Normalizer, obs, action, next_obs
    ) -> Array:
        """`loss` of the parameters adapted by `step`, without forming them."""
        pred = adapted_forward(params, step, self.inputs(norm, obs, action))
        return _mse(pred, self.scaled_targets(norm, obs, next_obs), None)


def _ordered(params: Params) -> list[dict]:
    return [params[f"Dense_{i}"] for i in range(len(params))]


def _mse(pred: Array, y: Array, mask: Array | None) -> Array:
    """Mean squared error over the output dims, averaged over the rows where mask is 1 (all if
    None); 0 when no row is valid."""
    err = jnp.mean((pred - y) ** 2, axis=-1)
    if mask is None:
        return jnp.mean(err)
    m = mask.astype(err.dtype)
    return jnp.sum(err * m) / jnp.maximum(jnp.sum(m), 1.0)


class MetaMetrics(NamedTuple):
    pre_loss: Array  # L_future(theta): the meta-parameters without adaptation
    post_loss: Array  # L_future(theta'): after the inner step on the past M (the objective)


def make_meta_loss(model: DynamicsModel, past: int, inner_lr: float) -> Callable:
    """`meta_loss(params, norm, windows [W, M + K]) -> (mean post-adaptation loss, metrics)`."""

    def one_window(params, norm, w: Transitions):
        p, f = slice(0, past), slice(past, None)
        step = model.inner_step(params, norm, w.obs[p], w.action[p], w.next_obs[p], inner_lr)
        post = model.adapted_loss(params, step, norm, w.obs[f], w.action[f], w.next_obs[f])
        pre = model.loss(params, norm, w.obs[f], w.action[f], w.next_obs[f])
        return post, jax.lax.stop_gradient(pre)

    def meta_loss(params, norm, windows: Transitions):
        post, pre = jax.vmap(one_window, in_axes=(None, None, 0))(params, norm, windows)
        return jnp.mean(post), MetaMetrics(jnp.mean(pre), jnp.mean(post))

    return meta_loss


def make_meta_step(
    model: DynamicsModel, past: int, inner_lr: float, optimizer: optax.GradientTransformation
) -> Callable:
    """One outer Adam step: `step(params, opt_state, norm, windows) -> (params, opt_state,
    MetaMetrics)` (pure; jit it, or scan it)."""
    meta_loss = make_meta_loss(model, past, inner_lr)

    def step(params, opt_state, norm, windows: Transitions):
        (_, metrics), g = jax.value_and_grad(meta_loss, has_aux=True)(params, norm, windows)
        updates, opt_state = optimizer.update(g, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, metrics

    return step


def sample_windows(
    buf, key: Array, num_tasks: int, meta_batch: int, windows: int, length: int, horizon: int
) -> Transitions:
    """`windows` windows of `length` consecutive transitions from whole episodes of a per-task
    buffer (`pearl.buffers.TaskBuffer` whose capacity is a multiple of the episode length
    `horizon`, filled with whole episodes): `meta_batch` tasks are drawn, window i comes from task
    i mod meta_batch, then a stored episode and a start step uniformly. -> Transitions [W, L]."""
    k_t, k_e, k_s = jax.random.split(key, 3)
    tids = jax.random.choice(k_t, num_tasks, (meta_batch,), replace=meta_batch > num_tasks)
    rows = tids[jnp.arange(windows) % meta_batch]
    episodes = jnp.maximum(buf.size[rows] // horizon, 1)
    ep = jax.random.randint(k_e, (windows,), 0, episodes)
    start = jax.random.randint(k_s, (windows,), 0, horizon - length + 1)
    idx = (ep * horizon + start)[:, None] + jnp.arange(length)[None, :]
    return jax.tree_util.tree_map(lambda b: b[rows[:, None], idx], buf.data)
