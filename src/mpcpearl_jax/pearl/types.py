"""Data that buffers, collection, evaluation and the learner share: a batch of transitions and
the context rows (s, a, r, s') built from it. Importing this module pulls in nothing else of
the package."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array


class Transitions(NamedTuple):
    """A batch of transitions; leading shape [...] e.g. [MB, B]."""

    obs: Array  # [..., O]
    action: Array  # [..., A] normalized
    reward: Array  # [...] unscaled
    next_obs: Array  # [..., O]
    done: Array  # [...] 1.0 on true termination (never in these tasks: time limits bootstrap)
    # [...] 1.0 where the MPC acted: kept only when the learner imitates it (`pearl.imitation`);
    # None (no leaf) otherwise
    expert: Array | None = None


def context_from(t: Transitions) -> Array:
    """Context rows (s, a, r, s') [..., 2 O + A + 1] with the unscaled reward (method §7)."""
    return jnp.concatenate([t.obs, t.action, t.reward[..., None], t.next_obs], axis=-1)
