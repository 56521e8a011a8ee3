"""The library's entries above every mode: `evaluate` (a run folder or loaded policies, or the
GP-MPC baseline, on a task source; `mpcpearl_jax.evaluate`)."""
