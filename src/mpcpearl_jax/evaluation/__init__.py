"""Meta-test evaluation: rollouts of a policy adapting to new tasks (Algorithm 2, `evaluate`),
the method's metrics (`metrics`, paper §VI-A), scoring a run on task sets (`scoring`), the
controller runners of the evaluation command (`runners`), the tables and figures of a run
(`report`, `viz`, `animate`), and a trained run's final evaluation (`final`, which ranks above
the run session whose folder it reads)."""
