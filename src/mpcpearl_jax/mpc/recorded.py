"""MPC problems recorded from training (`tests/data/mpc_problems.npz`, written by
`benchmarks.record_mpc_problems`): the data of the SQP's convergence curve (`lab.convergence`),
its tests and the MPC's benchmarks.

A file keeps, per problem, the pose, goal, static obstacles, the GP prediction's per-stage mean
and variance of each person and the warm-start plan (float32), a key seed per problem from which
the M samples are drawn again (`regenerate`), and the solver's settings as JSON ("params": the
`SolverParams` fields and OSQP's settings under "osqp_settings").
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from mpcpearl_jax.mpc.problem import RowProblem, SolverParams
from mpcpearl_jax.mpc.qp_osqp import OSQPSettings


def params_record(params: SolverParams, qp: OSQPSettings) -> dict[str, Any]:
    """The "params" JSON of a problem file: the problem's fields and OSQP's settings."""
    return {**dataclasses.asdict(params), "osqp_settings": list(dataclasses.asdict(qp).items())}


def solver_params_of(data) -> SolverParams:
    """The SolverParams stored in a problem file (fields added since: the MPCConfig default)."""
    d = {"multi_start": "off", **json.loads(str(data["params"]))}
    d.pop("osqp_settings", None)
    return SolverParams(**d)


def qp_settings_of(data) -> OSQPSettings:
    """OSQP's settings stored in a problem file (its setup-only flags left out)."""
    stored = dict(json.loads(str(data["params"]))["osqp_settings"])
    names = {f.name for f in dataclasses.fields(OSQPSettings)}
    return OSQPSettings(**{k: v for k, v in stored.items() if k in names})


def regenerate(data, num_samples: int) -> RowProblem:
    """RowProblem batch (float32, leading axis N) of a problem file: samples drawn from the stored
    mean and variance with key PRNGKey(seed) per problem (`gp.sample_predictions`)."""
    import jax

    from mpcpearl_jax.mpc.gp import sample_predictions

    keys = jax.vmap(jax.random.PRNGKey)(np.asarray(data["seed"]))
    draw = jax.vmap(lambda k, m, v: sample_predictions(k, m, v, num_samples))
    samples = np.asarray(draw(keys, data["mean"], data["var"]))
    return RowProblem(
        np.asarray(data["x0"]),
        np.asarray(data["goal"]),
        samples,
        np.asarray(data["valid"]),
        np.asarray(data["static_lo"]),
        np.asarray(data["static_hi"]),
        np.asarray(data["static_radius"]),
    )


@dataclasses.dataclass
class Recorded:
    """A problem file loaded: its arrays (data), the solver's params and OSQP settings, and the
    regenerated problems (batch, float32, leading axis N)."""

    data: dict[str, np.ndarray]
    params: SolverParams
    qp: OSQPSettings
    batch: RowProblem

    def __len__(self) -> int:
        return int(self.batch.x0.shape[0])

    def row(self, i: int) -> tuple[RowProblem, np.ndarray | None]:
        """Problem i in float64 and its warm-start plan (None: a cold start), as the SQP gets
        them from the bridge."""
        prob = RowProblem(
            *(np.asarray(a[i], np.float64 if a.dtype.kind == "f" else None) for a in self.batch)
        )
        has = bool(self.data["has_init"][i])
        return prob, (np.asarray(self.data["u_init"][i], np.float64) if has else None)


def load(path: str | Path) -> Recorded:
    """Read a problem file and draw its samples again."""
    with np.load(path) as f:
        data = {k: f[k] for k in f.files}
    params = solver_params_of(data)
    return Recorded(data, params, qp_settings_of(data), regenerate(data, params.num_samples))
