"""Configuration of the risk-aware GP-MPC (method §6, paper eq. (4)), validated at construction."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from mpcpearl_jax import validate as v

GP_MODES = ("fit", "fixed")
# the SQP's extra starts (`problem.starts`): none, only when the first start's plan is unsafe or
# its QP failed, or always (the safe plan of lowest exact merit is kept)
MULTI_STARTS = ("off", "on_failure", "always")
SQP_ITERS_MAX = 1000


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
    # SQP (on the host, its QPs on OSQP: `mpc.sqp`). The defaults run it to convergence, as
    # the paper's NLP solver: it ends on a step below `sqp_step_tol` or where the line search
    # finds no decrease, median 0.03 % above the best plan known on problems recorded from
    # training (docs/method.md §6); the presets other than `paper` cap it at 5 QPs
    sqp_iters: int = 100  # at most this many QPs per call (the best iterate is kept)
    sqp_step_tol: float = 1e-4  # stop early when the accepted input step is below this (inf-norm)
    trust_v: float = 2.0  # trust region on the speed, m/s (method §6 suggests ~1; 2 did better)
    trust_steer: float = 0.35  # trust region on the steering angle, rad (chosen on validation)
    slack_penalty: float = 2000.0  # L1 weight of the static and CVaR slacks (exact penalty)
    qp_tail_samples: int = 20  # T: samples per stage with the largest loss that enter each QP
    line_search_steps: int = 8  # step sizes 1, 1/2, 1/4, ... on the exact SAA merit
    cold_speed: float = 2.5  # speed of the cold-start plan, m/s
    unsafe_tol: float = 0.02  # first-stage violation (m) above which a plan counts as unsafe
    # extension (off = method §6): an unsafe plan is re-solved once from the least-violating first
    # move of a 3 x 3 input grid; a plan whose first move is as safe as the best of that grid is
    # used (reason "least_violation") instead of falling back
    unsafe_recovery: bool = False
    # extension (off = method §6): also run the SQP from a cold start and from standing still
    # (MULTI_STARTS), keeping the safe plan of lowest exact merit
    multi_start: str = "off"
    # the QP backend OSQP's own settings (read by `mpc.qp_osqp.OSQPSettings.from_config` only)
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
    # worker processes that solve a call's fired rows side by side (`mpc.pool.pool_size`): 1, in
    # the calling process; N > 1, a pool of N, at most one per core this process may use; 0, one
    # per core, at most 8. A call with one fired row solves it in the calling process
    n_workers: int = 1
    # with the pool: seconds a call waits for its rows; a row whose worker dies or is not done by
    # then falls back (reason "worker_lost") and the pool is replaced (`mpc.host`)
    worker_timeout_s: float = 60.0

    def __post_init__(self) -> None:
        v.ints(
            self,
            "horizon",
            "num_samples",
            "n_adapt",
            "sqp_iters",
            "osqp_max_iter",
            "n_gp",
            "qp_tail_samples",
        )
        v.ints(
            self,
            "n_workers",
            "line_search_steps",
            "gp_fit_steps",
            "osqp_check_termination",
            "osqp_adaptive_rho_interval",
            lo=0,
        )
        v.flags(self, "unsafe_recovery", "osqp_polish")
        v.check(
            v.is_number(self.alpha) and 0.0 < self.alpha < 1.0,
            self,
            "alpha",
            f"must lie in (0, 1), got {self.alpha!r}",
        )
        v.check(
            v.is_number(self.steer_max) and 0.0 < self.steer_max < math.pi / 2,
            self,
            "steer_max",
            f"must lie in (0, pi/2), got {self.steer_max!r}",
        )
        v.positive(
            self,
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
            "worker_timeout_s",
        )
        v.nonnegative(
            self, "delta_cvar", "terminal_weight", "sqp_step_tol", "unsafe_tol", "gp_static_tol"
        )
        v.nonnegative(self, "r_safe", none_ok=True)
        v.positive(self, "v_max", none_ok=True)
        v.one_of(self, "gp_mode", GP_MODES)
        v.one_of(self, "multi_start", MULTI_STARTS)
        v.check(
            self.sqp_iters <= SQP_ITERS_MAX,
            self,
            "sqp_iters",
            f"must lie in [1, {SQP_ITERS_MAX}], got {self.sqp_iters!r}",
        )
        v.check(
            math.isfinite(self.sqp_step_tol) and self.sqp_step_tol <= self.trust_v,
            self,
            "sqp_step_tol",
            f"must lie in [0, trust_v = {self.trust_v}] (a step is at most the trust region), "
            f"got {self.sqp_step_tol!r}",
        )
        v.check(
            self.num_samples * (1.0 - self.alpha) >= 1.0,
            self,
            "num_samples",
            "num_samples * (1 - alpha) must be >= 1 for an SAA-CVaR",
        )

    def replace(self, **changes: Any) -> MPCConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
