"""The learning-curve command of earlier records: `python -m experiments.learning ARGS` runs
`python -m experiments.restaurant ARGS` (the family of --env, or of --config's run), whose
--minutes M [--eval-minutes X] trains on a time budget and writes the learning curve
(`mpcpearl_jax.training.budget`)."""

import sys

from experiments.common import main

if __name__ == "__main__":
    sys.exit(main("restaurant", command="learning", from_config=True))
