"""Meta-test evaluation: rollouts of a policy adapting to new tasks (Algorithm 2, `evaluate`),
the method's metrics (`metrics`, paper §VI-A), scoring a run on task sets (`scoring`), the
controller runners (`runners`) and the pieces of `mpcpearl_jax.evaluate` below the run loading
(`plan`: the evaluated tasks, the MPC settings, the record, figures), and the tables and animations
of a run (`report`, `animate`; trajectory figures: `envs.drawing`). A trained run's final
evaluation is the end of training (`training.final`)."""
