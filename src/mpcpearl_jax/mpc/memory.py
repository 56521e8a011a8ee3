"""Each row's previous plan on the host (method §6): the warm start of its next solve and its
fallback (`mpc.rows`), kept per shard of a batch by the bridge's host side (`mpc.host`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from mpcpearl_jax.mpc.rows import NO_PLAN, shifted


@dataclasses.dataclass
class PlanMemory:
    """Each row's previous plan, plans [B, K, 2] physical, and the step it was made at, plan_t
    [B] (`NO_PLAN`: none); episode: the stamp of the batch of episodes the plans belong to."""

    plans: np.ndarray
    plan_t: np.ndarray
    episode: tuple[int, ...] | None = None

    @classmethod
    def empty(cls, batch: int, horizon: int) -> PlanMemory:
        return cls(np.zeros((batch, horizon, 2)), np.full(batch, NO_PLAN, np.int64))

    def start(self, stamp: tuple[int, ...]) -> None:
        """A call's episode stamp (given flag, stamp...): a new batch of episodes forgets every
        plan; no stamp (flag 0) keeps them."""
        if stamp[0] and stamp != self.episode:
            self.plan_t[:] = NO_PLAN
            self.episode = stamp

    def warm(self, b: int, t: int) -> np.ndarray | None:
        """Row b's previous plan shifted by one step if it was made at t - 1, else None."""
        if self.plan_t[b] != t - 1:
            return None
        return shifted(self.plans[b])

    def forget(self) -> None:
        """Forget every row's plan (the next solves start cold)."""
        self.plan_t[:] = NO_PLAN
