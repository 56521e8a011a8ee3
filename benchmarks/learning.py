"""`python -m benchmarks.learning ...` runs `python -m experiments.learning ...` (the
learning-curve harness is an experiment driver and lives in experiments/; this name keeps the
commands recorded with the committed results valid)."""

import sys

from experiments.learning import main

if __name__ == "__main__":
    sys.exit(main())
