"""MPC-PEARL on the sidewalk tasks (method §4): `python -m experiments.sidewalk [--data FILE]`.

Without --data the built-in synthetic crowd is used (runs on a fresh machine); with an ETH/UCY
file (e.g. UCY Zara 01) the 31 ten-second windows of the scene become 25 training and 6 test
tasks. Online adaptation (one episode, z re-inferred every t_update steps) is the headline
evaluation here, as in the paper; the MPC speed cap is the env's v_max (1.8 m/s).
"""

import sys

from experiments.common import main

if __name__ == "__main__":
    sys.exit(main("sidewalk"))
