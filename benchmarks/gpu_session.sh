#!/usr/bin/env bash
# One accelerator session: the MPC solvers side by side, under 9 minutes on one GPU (each step
# under its own time limit, so that one slow step leaves the others their time).
#
#   bash benchmarks/gpu_session.sh OUT_DIR            # the budgets below
#   GPU_SESSION_TINY=1 bash benchmarks/gpu_session.sh OUT_DIR   # tiny budgets: a check of each step
#
# Writes under OUT_DIR:
#   (g) gate.json: the device solver on every recorded problem against OSQP (benchmarks.mpc_gate);
#   (a) mpc_solvers.json: per-call latency of the OSQP and device solvers, batch 1 and 16;
#   (b) gp_mpc-device/: GP-MPC on the authors' 25 test scenarios with the device solver (OSQP's
#       too with GPMPC_SOLVERS="osqp device"; its figures are in the README's summary table)
#       (skipped when SCENARIOS, default ../shared/data/mpc-pearl-scenarios, is absent);
#   (c) recipe-osqp/, recipe-device/: the recommended recipe with 8 seeds (metrics.jsonl logs
#       collect_s and update_s per iteration), OSQP with 8 host workers against the device solver;
#   (d) paper-device/: the paper preset, one seed, with the device solver;
#   and summary.txt (the per-iteration means of each run), log.txt (everything printed).
# Environment: PYTHON (default python), SCENARIOS, GPMPC_SOLVERS, RECIPE_MIN (1.25), PAPER_MIN (0.75).
set -uo pipefail

OUT=${1:?usage: gpu_session.sh OUT_DIR}
mkdir -p "$OUT"
PY=${PYTHON:-python}
SCEN=${SCENARIOS:-../shared/data/mpc-pearl-scenarios}
RECIPE_MIN=${RECIPE_MIN:-1.25}
PAPER_MIN=${PAPER_MIN:-0.75}
BENCH=(--batches 1 16 --calls 2)
GPMPC=()
if [[ "${GPU_SESSION_TINY:-0}" == 1 ]]; then
  RECIPE_MIN=0.05 PAPER_MIN=0.05
  BENCH=(--tiny --batches 1 2 --calls 2)
  GPMPC=(--max-tasks 2)
fi
exec > >(tee -a "$OUT/log.txt") 2>&1
export PYTHONPATH="$PWD/src:$PWD${PYTHONPATH:+:$PYTHONPATH}"
stamp() { echo "== $(date -u +%H:%M:%S) $*"; }
GATE=()
[[ "${GPU_SESSION_TINY:-0}" == 1 ]] && GATE=(--rows 4 --chunk 4)

stamp "(g) gate: every recorded problem, device solver against OSQP"
timeout 100 $PY -m benchmarks.mpc_gate "${GATE[@]}" --out "$OUT/gate.json" || stamp "(g) failed or timed out"
stamp "(a) solver latency"
timeout 45 $PY -m benchmarks.mpc_solvers "${BENCH[@]}" --out "$OUT" || stamp "(a) failed or timed out"

if [[ -d "$SCEN" ]]; then
  for solver in ${GPMPC_SOLVERS:-device}; do  # OSQP's figures: the README's summary table
    stamp "(b) GP-MPC, authors' test scenarios, solver $solver"
    timeout 100 $PY -m experiments.gp_mpc --scenarios "$SCEN" --split test --set solver=$solver \
      "${GPMPC[@]}" --out "$OUT/gp_mpc-$solver" || stamp "(b) failed or timed out"
  done
else
  stamp "(b) skipped: no scenarios at $SCEN"
fi

RECIPE=(--preset recipe --eps 0.2 --seeds 8
  --eval-minutes "$RECIPE_MIN" --policy-only --no-progress --overwrite)
stamp "(c) recipe, 8 seeds, OSQP with 8 workers"
timeout 110 $PY -m experiments.restaurant "${RECIPE[@]}" --minutes "$RECIPE_MIN" \
  --set mpc.solver=osqp --set mpc.n_workers=8 --out "$OUT/recipe-osqp"
stamp "(c) recipe, 8 seeds, device solver"
timeout 150 $PY -m experiments.restaurant "${RECIPE[@]}" --minutes "$RECIPE_MIN" \
  --set mpc.solver=device --out "$OUT/recipe-device"
stamp "(d) paper preset, one seed, device solver"
timeout 80 $PY -m experiments.restaurant --preset paper --eps 0.2 --minutes "$PAPER_MIN" \
  --eval-minutes "$PAPER_MIN" --policy-only --no-progress --overwrite \
  --set mpc.solver=device --out "$OUT/paper-device"

stamp "summary"
$PY - "$OUT" <<'EOF' | tee "$OUT/summary.txt"
import json, statistics, sys
from pathlib import Path

out = Path(sys.argv[1])
for run in ("recipe-osqp", "recipe-device", "paper-device"):
    path = out / run / "metrics.jsonl"
    if not path.exists():
        print(f"{run}: no metrics.jsonl")
        continue
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if "collect_s" in r][1:] or rows  # the first holds the compilation
    if not rows:
        print(f"{run}: no iteration finished")
        continue
    mean = lambda k: statistics.mean(r.get(k, float("nan")) for r in rows)  # noqa: E731
    it = mean("collect_s") + mean("update_s")
    print(
        f"{run}: {len(rows)} iterations, collect {mean('collect_s'):.3f} s, update "
        f"{mean('update_s'):.3f} s, collection share {mean('collect_s') / it:.0%}"
    )
EOF
stamp "done"
