"""MPC-PEARL on the restaurant tasks: `python -m experiments.restaurant [--preset ...]`.

Trains (default preset: a few minutes on a laptop CPU), evaluates on the 24 unseen test tasks
(after two adaptation episodes, and online) and the OOD tasks, and writes metrics.jsonl,
learning_curves.png, trajectory figures and results.json into --out.
"""

import sys

from experiments.common import main

if __name__ == "__main__":
    sys.exit(main("restaurant"))
