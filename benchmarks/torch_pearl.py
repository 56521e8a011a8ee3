"""A straightforward PyTorch PEARL gradient step: the comparison baseline of `pearl_step.py`.

It follows the authors' PyTorch PEARL (`PEARLSoftActorCritic._take_step`, method §7): a context
encoder (3 x 200) giving a mean and a softplus variance per transition, the product-of-Gaussians
posterior (variance clamped >= 1e-7), a reparameterised z, and SAC with a value net V and its
soft-updated target (tau 0.005), twin Q, and a tanh-Gaussian policy (log-std clamped to [-20, 2],
log-prob from the pre-tanh sample, mean/std regularisers 1e-3), reward scale 100, gamma 0.99, and
one Adam (lr 3e-4) per network. The encoder learns from the Q loss plus 0.1 * KL(q(z|c) || N(0, I))
summed over tasks; V and the policy see z detached.

One deliberate difference from the authors' code: the policy loss evaluates Q with a detached z,
so its backward pass does not walk through the encoder. The authors' code computes those encoder
gradients and then discards them (they are zeroed before the next use), so the update is the same
and the baseline is only made cheaper.

Only the update is timed; batches are given as tensors (no replay-buffer sampling).
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import nn
from torch.nn import functional as F


@dataclasses.dataclass(frozen=True)
class TorchPearlSizes:
    """The PEARL settings the baseline needs (names and defaults as in `PearlConfig`)."""

    latent_dim: int = 10
    hidden: tuple[int, ...] = (300, 300, 300)
    encoder_hidden: tuple[int, ...] = (200, 200, 200)
    lr: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005
    reward_scale: float = 100.0
    kl_weight: float = 0.1
    policy_mean_reg: float = 1e-3
    policy_std_reg: float = 1e-3
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    min_posterior_var: float = 1e-7

    @classmethod
    def like(cls, cfg: object) -> TorchPearlSizes:
        """Copy the matching fields of another config (e.g. `PearlConfig`)."""
        names = [f.name for f in dataclasses.fields(cls)]
        return cls(**{n: getattr(cfg, n) for n in names if hasattr(cfg, n)})


def mlp(in_dim: int, hidden: tuple[int, ...], out_dim: int, init_w: float = 3e-3) -> nn.Sequential:
    """ReLU MLP with the authors' init: fan-in uniform hidden layers, small uniform last layer."""
    layers: list[nn.Module] = []
    d = in_dim
    for h in hidden:
        lin = nn.Linear(d, h)
        bound = 1.0 / math.sqrt(d)
        nn.init.uniform_(lin.weight, -bound, bound)
        nn.init.constant_(lin.bias, 0.1)
        layers += [lin, nn.ReLU()]
        d = h
    last = nn.Linear(d, out_dim)
    nn.init.uniform_(last.weight, -init_w, init_w)
    nn.init.uniform_(last.bias, -init_w, init_w)
    layers.append(last)
    return nn.Sequential(*layers)


class TorchPearl:
    """Networks, optimisers and one PEARL gradient step.

    Shapes: obs [MB, B, O], action [MB, B, A], reward [MB, B], next_obs [MB, B, O], done [MB, B],
    context [MB, C, 2 O + A + 1].
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        sizes: TorchPearlSizes,
        seed: int = 0,
        device: str = "cpu",
    ):
        torch.manual_seed(seed)
        s = sizes
        self.s = s
        z, h = s.latent_dim, s.hidden
        context_dim = 2 * obs_dim + action_dim + 1
        self.encoder = mlp(context_dim, s.encoder_hidden, 2 * z)
        self.qf1 = mlp(obs_dim + action_dim + z, h, 1)
        self.qf2 = mlp(obs_dim + action_dim + z, h, 1)
        self.vf = mlp(obs_dim + z, h, 1)
        self.target_vf = mlp(obs_dim + z, h, 1)
        self.target_vf.load_state_dict(self.vf.state_dict())
        self.policy = mlp(obs_dim + z, h, 2 * action_dim)
        for name in ("encoder", "qf1", "qf2", "vf", "target_vf", "policy"):
            getattr(self, name).to(device)
        adam = lambda m: torch.optim.Adam(m.parameters(), lr=s.lr)
        self.opt = {
            name: adam(getattr(self, name)) for name in ("encoder", "qf1", "qf2", "vf", "policy")
        }

    # ---------------------------------------------------------------- parts
    def posterior(self, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Product of per-transition Gaussians: (mean, variance), each [MB, Z]."""
        params = self.encoder(context)
        z = self.s.latent_dim
        mu, var = params[..., :z], F.softplus(params[..., z:])
        var = var.clamp(min=self.s.min_posterior_var)
        post_var = 1.0 / (1.0 / var).sum(dim=1)
        post_mu = post_var * (mu / var).sum(dim=1)
        return post_mu, post_var

    def act(self, obs_z: torch.Tensor):
        """Reparameterised tanh-Gaussian sample: (action, mean, log_std, log_prob [N, 1])."""
        out = self.policy(obs_z)
        mean, log_std = out.chunk(2, dim=-1)
        log_std = log_std.clamp(self.s.log_std_min, self.s.log_std_max)
        std = log_std.exp()
        pre_tanh = mean + std * torch.randn_like(mean)
        action = torch.tanh(pre_tanh)
        normal = torch.distributions.Normal(mean, std)
        log_prob = normal.log_prob(pre_tanh) - torch.log(1 - action.pow(2) + 1e-6)
        return action, mean, log_std, log_prob.sum(dim=-1, keepdim=True)

    # ----------------------------------------------------------------- step
    def step(self, obs, action, reward, next_obs, done, context) -> dict[str, float]:
        """One gradient step of every network (the authors' order); returns the losses."""
        s = self.s
        mb, b, _ = obs.shape
        post_mu, post_var = self.posterior(context)
        z = post_mu + post_var.sqrt() * torch.randn_like(post_mu)
        task_z = z.repeat_interleave(b, dim=0)  # [MB * B, Z]
        obs, action, next_obs = (x.reshape(mb * b, -1) for x in (obs, action, next_obs))
        reward, done = reward.reshape(mb * b, 1), done.reshape(mb * b, 1)

        zd = task_z.detach()
        new_action, mean, log_std, log_pi = self.act(torch.cat([obs, zd], dim=1))
        q1 = self.qf1(torch.cat([obs, action, task_z], dim=1))
        q2 = self.qf2(torch.cat([obs, action, task_z], dim=1))
        v_pred = self.vf(torch.cat([obs, zd], dim=1))
        with torch.no_grad():
            target_v = self.target_vf(torch.cat([next_obs, task_z], dim=1))

        # Encoder: KL to the prior (summed over tasks and latent dims) + the Q loss below.
        for name in ("encoder", "qf1", "qf2"):
            self.opt[name].zero_grad()
        kl = 0.5 * (post_var + post_mu.pow(2) - 1.0 - post_var.log()).sum()
        q_target = reward * s.reward_scale + (1.0 - done) * s.gamma * target_v
        qf_loss = ((q1 - q_target) ** 2).mean() + ((q2 - q_target) ** 2).mean()
        (s.kl_weight * kl + qf_loss).backward()
        for name in ("qf1", "qf2", "encoder"):
            self.opt[name].step()

        # V towards min Q(s, a~pi) - log pi (temperature 1 / reward_scale folded into the reward).
        obs_a_z = torch.cat([obs, new_action, zd], dim=1)
        min_q_new = torch.min(self.qf1(obs_a_z), self.qf2(obs_a_z))
        v_target = (min_q_new - log_pi).detach()
        vf_loss = F.mse_loss(v_pred, v_target)
        self.opt["vf"].zero_grad()
        vf_loss.backward()
        self.opt["vf"].step()
        with torch.no_grad():
            for p_t, p in zip(self.target_vf.parameters(), self.vf.parameters(), strict=True):
                p_t.mul_(1.0 - s.tau).add_(p, alpha=s.tau)

        # Policy: KL(pi || exp Q) plus the mean / log-std regularisers.
        policy_loss = (log_pi - min_q_new).mean()
        policy_loss = policy_loss + s.policy_mean_reg * mean.pow(2).mean()
        policy_loss = policy_loss + s.policy_std_reg * log_std.pow(2).mean()
        self.opt["policy"].zero_grad()
        policy_loss.backward()
        self.opt["policy"].step()
        losses = {"qf_loss": qf_loss, "vf_loss": vf_loss, "policy_loss": policy_loss, "kl": kl}
        return {k: v.item() for k, v in losses.items()}


def random_batch(
    mb: int, b: int, c: int, obs_dim: int, action_dim: int, seed: int = 0
) -> tuple[torch.Tensor, ...]:
    """Random (obs, action, reward, next_obs, done, context) of the shapes the step takes."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *shape: torch.rand(*shape, generator=g) * 2 - 1
    obs, next_obs = u(mb, b, obs_dim), u(mb, b, obs_dim)
    action, reward = u(mb, b, action_dim), u(mb, b)
    done = (torch.rand(mb, b, generator=g) < 0.0125).float()
    context = u(mb, c, 2 * obs_dim + action_dim + 1)
    return obs, action, reward, next_obs, done, context
