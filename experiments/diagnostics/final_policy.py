"""The last iteration's own policy of a run trained with `train.keep_best`, as a run folder that
`experiments.evaluate` reads: `python -m experiments.diagnostics.final_policy RUN WORK --out DIR`.

A `keep_best` run reports, saves and exports its kept policy (docs/extensions.md, "Kept
policy"); the policy that training arrived at is only in its checkpoints. This writes that one:
RUN is the run's results folder (config.json, network.json), WORK the folder whose checkpoints/
hold its training state (the campaign's `runs/campaign/<entry>`); DIR receives config.json,
network.json and policy.msgpack with the {policy, encoder} of the newest checkpoint's learner,
so that the kept and the final policy of one training can be evaluated on the same tasks:

    python -m experiments.diagnostics.final_policy results/restaurant/screen/keep-s2 \\
        runs/campaign/learner-keep-s2 --out runs/final/keep-s2
    python -m experiments.evaluate runs/final/keep-s2 --split val --task-seeds 1-8 \\
        --figures none --out results/restaurant/screen/keep-s2/eval/final-policy-val-seeds1-8
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m experiments.diagnostics.final_policy", description=__doc__.splitlines()[0]
    )
    p.add_argument("run", type=Path, help="the run's results folder (config.json, network.json)")
    p.add_argument("work", type=Path, help="the folder whose checkpoints/ hold the training state")
    p.add_argument("--out", type=Path, required=True, help="the run folder to write")
    args = p.parse_args(argv)

    from mpcpearl_jax.distributed import to_host
    from mpcpearl_jax.errors import CheckpointError, ConfigError
    from mpcpearl_jax.pearl.learner import acting_params
    from mpcpearl_jax.training.checkpoint import (
        CONFIG_FILE,
        NETWORK_FILE,
        POLICY_FILE,
        Checkpointer,
        load_config,
        save_params,
    )
    from mpcpearl_jax.training.trainer import Trainer

    try:
        cfg = load_config(args.run)
        if not cfg.train.keep_best:
            raise ConfigError(f"{args.run}/config.json: not a keep_best run (train.keep_best off)")
        # the state's layout does not depend on eps; eps = 0 builds no MPC bridge
        trainer = Trainer(cfg.replace(train=dataclasses.replace(cfg.train, eps=0.0)))
        ck = Checkpointer(args.work)
        state = ck.restore(template=trainer.init_state())
        step = ck.restored_step
        ck.close()
        trainer.close()
    except (ConfigError, CheckpointError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    for name in (CONFIG_FILE, NETWORK_FILE):
        shutil.copyfile(args.run / name, args.out / name)
    save_params(args.out / POLICY_FILE, to_host(acting_params(state.learner.params)))
    print(f"wrote {args.out / POLICY_FILE}: the learner's policy at iteration {step}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
