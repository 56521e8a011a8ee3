"""GrBAL baseline (Nagabandi et al., ICLR 2019): `python -m experiments.grbal [--env ...]`.

    python -m experiments.grbal --env restaurant --preset cpu --out runs/grbal-cpu
    python -m experiments.grbal --env sidewalk --data path/to/crowds_zara01.txt --preset cpu
    python -m experiments.grbal --out runs/grbal-cpu --preset cpu --resume   # continue
    python -m experiments.grbal --preset cpu --minutes 16   # train for 16 minutes, then evaluate

Meta-trains the learned dynamics model (one inner SGD step on M past transitions, scored on the
K next), collecting with MPPI on the adapted model, then evaluates on the test tasks (after two
adaptation episodes, and online) and the OOD tasks with the method §8 metrics. Writes
metrics.jsonl, checkpoints, learning_curves.png, trajectory figures and results.json into --out
(the files of the other methods: `python -m lab.compare` reads them).
Any field of `GrbalConfig` can be changed with --set grbal.FIELD=VALUE, a NavConfig field with
--set env.FIELD=VALUE (JSON values).
"""

from __future__ import annotations

import sys

from mpcpearl_jax.cli import train


def main(argv: list[str] | None = None) -> int:
    """The command: the training command of the registered algorithm "grbal"
    (`mpcpearl_jax.cli.train.main`, through `mpcpearl_jax.train`)."""
    return train.main("restaurant", argv, algorithm="grbal", description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
