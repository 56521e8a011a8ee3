"""Meta-test evaluation: rollouts of a policy adapting to new tasks (Algorithm 2, `evaluate`),
the method's metrics (`metrics`, paper §VI-A), scoring a run on task sets (`scoring`), the
controller runners of the evaluation command (`runners`) and its work once its command line is
read (`command`: the evaluated tasks, the record, tables, figures), and the tables and animations
of a run (`report`, `animate`; trajectory figures: `envs.drawing`). A trained run's final
evaluation is the end of training (`training.final`)."""
