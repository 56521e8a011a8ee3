"""Configuration of the risk-aware GP-MPC (method §6, paper eq. (4)), validated at construction."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from mpcpearl_jax.errors import ConfigError

GP_MODES = ("fit", "fixed")


def _fail(field: str, msg: str) -> None:
    raise ConfigError(f"MPCConfig.{field}: {msg}")


@dataclasses.dataclass(frozen=True)
class MPCConfig:
    """Every parameter of the MPC and of the GP prediction (method §6).

    Problem (paper eq. (4)): horizon K, stage cost |p - g|^2_Q + u'Ru with Q, R from the env
    config, terminal |p_K - g|^2 weighted by `terminal_weight` * Q, one SAA-CVaR constraint per
    stage (eq. (4b)) over `num_samples` GP samples of the `n_adapt` nearest people, static
    obstacles as hard constraints (eq. (4c), L1-penalised slacks keep every QP feasible).

    `r_safe = None` takes the env's r_safe; `v_max = None` takes the env's v_max (the authors' code
    caps the MPC speed at 5).
    """

    # problem (paper eq. (4))
    horizon: int = 10  # K
    num_samples: int = 100  # M_SAA
    alpha: float = 0.95  # CVaR level (paper; authors' code 0.99)
    delta_cvar: float = 0.01  # delta_CVaR
    n_adapt: int = 2  # nearest people that enter the CVaR constraint
    r_safe: float | None = None
    v_max: float | None = 5.0
    steer_max: float = 1.5  # |delta| cap of the MPC (< pi/2, where tan(delta) diverges)
    terminal_weight: float = 20.0  # Q_f = terminal_weight * Q
    # SQP (host side, OSQP)
    sqp_iters: int = 2  # at most this many QPs per call
    sqp_step_tol: float = 0.05  # stop early when the accepted input step is below this (inf-norm)
    trust_v: float = 2.0  # trust region on the speed, m/s (method §6 suggests ~1; 2 did better)
    trust_steer: float = 0.35  # trust region on the steering angle, rad
    slack_penalty: float = 2000.0  # L1 weight of the static and CVaR slacks (exact penalty)
    qp_tail_samples: int = 20  # T: samples per stage with the largest loss that enter each QP
    line_search_steps: int = 3  # step sizes 1, 1/2, 1/4, ... on the exact SAA merit
    cold_speed: float = 2.5  # speed of the cold-start plan, m/s
    unsafe_tol: float = 0.02  # first-stage violation (m) above which a plan counts as unsafe
    # extension (off = method §6): an unsafe plan is re-solved once from the least-violating first
    # move of a 3 x 3 input grid; a plan whose first move is as safe as the best of that grid is
    # used (reason "least_violation") instead of falling back
    unsafe_recovery: bool = False
    osqp_eps_abs: float = 1e-3
    osqp_eps_rel: float = 1e-3
    osqp_max_iter: int = 200
    osqp_rho: float = 0.1
    osqp_check_termination: int = 5
    osqp_adaptive_rho_interval: int = 25
    osqp_polish: bool = False
    # GP prediction of people (paper appendix)
    n_gp: int = 10  # N_GP transitions of history
    gp_mode: str = "fit"  # "fit": max. marginal likelihood by `gp_fit_steps`; "fixed": values below
    gp_fit_steps: int = 20
    gp_fit_lr: float = 0.1
    gp_lengthscale: float = 1.0  # m (initial value in "fit" mode)
    gp_signal_std: float = 0.2  # m per step
    gp_noise_std: float = 0.01  # m per step
    gp_static_tol: float = 1e-4  # a person who moved less than this in the last step is static
    # execution
    n_workers: int = 1  # >1: solve fired rows in a process pool

    def __post_init__(self) -> None:
        for f in (
            "horizon",
            "num_samples",
            "n_adapt",
            "sqp_iters",
            "osqp_max_iter",
            "n_gp",
            "qp_tail_samples",
        ):
            v = getattr(self, f)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                _fail(f, f"must be an int >= 1, got {v!r}")
        for f in (
            "line_search_steps",
            "gp_fit_steps",
            "osqp_check_termination",
            "osqp_adaptive_rho_interval",
        ):
            v = getattr(self, f)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                _fail(f, f"must be an int >= 0, got {v!r}")
        if not isinstance(self.unsafe_recovery, bool):
            _fail("unsafe_recovery", f"must be true or false, got {self.unsafe_recovery!r}")
        if not (isinstance(self.n_workers, int) and self.n_workers >= 1):
            _fail("n_workers", f"must be an int >= 1, got {self.n_workers!r}")
        if not (0.0 < self.alpha < 1.0):
            _fail("alpha", f"must lie in (0, 1), got {self.alpha!r}")
        if not (0.0 < self.steer_max < math.pi / 2):
            _fail("steer_max", f"must lie in (0, pi/2), got {self.steer_max!r}")
        for f in (
            "trust_v",
            "trust_steer",
            "slack_penalty",
            "osqp_eps_abs",
            "osqp_eps_rel",
            "osqp_rho",
            "gp_fit_lr",
            "gp_lengthscale",
            "gp_signal_std",
            "gp_noise_std",
            "cold_speed",
        ):
            self._positive(f)
        for f in ("delta_cvar", "terminal_weight", "sqp_step_tol", "unsafe_tol", "gp_static_tol"):
            self._nonnegative(f)
        for f in ("r_safe", "v_max"):
            if getattr(self, f) is not None:
                (self._nonnegative if f == "r_safe" else self._positive)(f)
        if self.gp_mode not in GP_MODES:
            _fail("gp_mode", f"must be one of {GP_MODES}, got {self.gp_mode!r}")
        if self.num_samples * (1.0 - self.alpha) < 1.0:
            _fail("num_samples", "num_samples * (1 - alpha) must be >= 1 for an SAA-CVaR")

    def _positive(self, f: str) -> None:
        v = getattr(self, f)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            _fail(f, f"must be a positive finite number, got {v!r}")

    def _nonnegative(self, f: str) -> None:
        v = getattr(self, f)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            _fail(f, f"must be a non-negative finite number, got {v!r}")

    def replace(self, **changes: Any) -> MPCConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
