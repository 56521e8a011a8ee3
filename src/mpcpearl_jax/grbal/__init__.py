"""GrBAL baseline (Nagabandi et al., "Learning to Adapt in Dynamic, Real-World Environments
Through Meta-Reinforcement Learning", ICLR 2019): a learned dynamics model meta-trained for one
gradient step of adaptation, and MPPI on the adapted model. See docs/grbal.md.
"""

from mpcpearl_jax.grbal.config import PRESETS, GrbalConfig, GrbalExperimentConfig, preset
from mpcpearl_jax.grbal.model import DynamicsModel, ObsLayout, make_meta_step
from mpcpearl_jax.grbal.planner import Planner, mppi
from mpcpearl_jax.grbal.trainer import GrbalState, GrbalTrainer

__all__ = [
    "PRESETS",
    "DynamicsModel",
    "GrbalConfig",
    "GrbalExperimentConfig",
    "GrbalState",
    "GrbalTrainer",
    "ObsLayout",
    "Planner",
    "make_meta_step",
    "mppi",
    "preset",
]
