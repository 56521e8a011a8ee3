"""mpcpearl_jax: MPC-PEARL (meta-RL with event-triggered risk-aware MPC infusion) in JAX."""

from mpcpearl_jax.envs import make_env, make_tasks

__version__ = "0.1.0"

__all__ = ["make_env", "make_tasks", "__version__"]
