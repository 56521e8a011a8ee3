#!/usr/bin/env bash
# One GPU session: seconds per training iteration of the recommended recipe (8 seeds, with and
# without train.pipeline), of the main command's preset on the GPU and on the same machine's CPU,
# and of the paper preset; at most 555 s on one GPU, compilation included. Every step runs
# under its own time limit and the whole under a deadline (TOTAL_S), so that one slow step leaves
# the others their time; a training stopped at its limit keeps the iterations it finished
# (metrics.jsonl gets a row per iteration), and a minutes budget shrinks to the time left.
#
#   bash benchmarks/gpu_session.sh OUT_DIR                       # the budgets below
#   GPU_SESSION_TINY=1 JAX_PLATFORMS=cpu bash benchmarks/gpu_session.sh OUT_DIR
#                                       # tiny budgets: every step once on a CPU (a check)
#
# Writes under OUT_DIR:
#   machine.txt: the GPU, the host's cores and load, JAX's devices and the library versions;
#   (a) recipe/, recipe-pipeline/: the `recipe` preset, 8 seeds, eps 0.2, 8 host workers for the
#       MPC, RECIPE_MIN minutes each, without and with train.pipeline (the episodes of
#       iteration k + 1 collected beside the gradient steps of iteration k);
#   (b) default-gpu/, default-cpu/: one seed of the `default` preset (the main command's),
#       DEFAULT_ITERS iterations, on the GPU and on the same machine's CPU (JAX_PLATFORMS=cpu);
#   (c) paper/: the `paper` preset, one seed, eps 0.2, PAPER_MIN minutes;
#   (d) while time is left: pipeline.json (python -m benchmarks.pipeline: two `default` trainers
#       side by side, pipelined and not, PIPELINE_ITERS iterations) and collection-seeds8.json
#       (python -m benchmarks.collection --seeds 8);
#   summary.txt and summary.json (python -m benchmarks.gpu_summary: each run's median seconds per
#   iteration, collection and updates from metrics.jsonl, and the three GPU targets: recipe
#   <= 1.5 s per iteration, `default` >= 2x faster on the GPU than on the CPU, paper <= 1.5 s),
#   log.txt (everything printed) and records.tgz (every text record above, without policies
#   and figures: what to bring back and commit).
# A training is stopped once its training is done (curve.json written, or its last iteration
# logged), before the final evaluation, which the timings do not need (FINAL_EVAL=1 keeps it).
# Environment: PYTHON (default python), TOTAL_S (555), RECIPE_MIN (1.5), PAPER_MIN (2),
# DEFAULT_ITERS (6), PIPELINE_ITERS (8), FINAL_EVAL (0), JAX_COMPILATION_CACHE_DIR (default
# /tmp/gpu-session-jax-cache: the runs of one preset share compiled programs; "" for none).
#
# On the GPU machine (one H200, 16 host cores, no network; its image has JAX 0.11.2 with CUDA 13,
# flax, optax, chex, orbax-checkpoint, numpy, scipy, matplotlib, tqdm; python3 is 3.12):
#  1. Here, once: `bash ../shared/tools/device-wheels.sh` downloads the wheels the image lacks
#     (distrax, tfp-nightly, dm-tree, gast, decorator, osqp; 7.6 MiB) into .whl/, which it adds
#     to .git/info/exclude.
#  2. What travels (tracked and untracked-not-ignored files, plus the carried .whl) must stay
#     under 64 MiB. The tree is about 60 MiB, 58 of them results/ (trained runs and figures; the
#     script reads none of it), so take results/ out of the working tree for the call, and put
#     it back after (results/ is absent from the checkout meanwhile; git status stays clean):
#       git sparse-checkout set --no-cone '/*' '!/results/'    # before
#       git sparse-checkout disable                            # after
#     Size check: git ls-files -co --exclude-standard -z | du -cb --files0-from=- 2>/dev/null |
#     tail -1 (about 2.4 MB without results/), and du -sb .whl.
#  3. One call, carry [".whl"], timeout_s 600 (the script ends by TOTAL_S = 555 s; console.txt
#     comes back even if the call is cut short):
#       python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
#         --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD/src:$PWD \
#         XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1 || exit;
#       PYTHON=python3 bash benchmarks/gpu_session.sh /tmp/gpu 2>&1 | tee $OUT/console.txt;
#       cp /tmp/gpu/summary.txt /tmp/gpu/summary.json /tmp/gpu/records.tgz $OUT/
#     (a call brings back at most 8 files, hence records.tgz).
#  4. Here: mkdir -p benchmarks/results/gpu-h200-training && tar -xzf FILES_AT/records.tgz -C
#     benchmarks/results/gpu-h200-training (FILES_AT: the reply's files_at), commit that folder
#     and run python -m lab.table (the README's speed table reads its summary.json).
set -uo pipefail

OUT=${1:?usage: gpu_session.sh OUT_DIR}
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
PY=${PYTHON:-python}
TINY=${GPU_SESSION_TINY:-0}
FINAL_EVAL=${FINAL_EVAL:-0}
RECIPE_MIN=${RECIPE_MIN:-1.5}
PAPER_MIN=${PAPER_MIN:-2}
DEFAULT_ITERS=${DEFAULT_ITERS:-6}
PIPELINE_ITERS=${PIPELINE_ITERS:-8}
TOTAL_S=${TOTAL_S:-555}
SEEDS=8
WORKERS=8
MIN_STEP=40     # a step with less time left is skipped
STARTUP_S=35    # a minutes run's seconds besides its budget: imports, trainer, evaluation at 0
SLACK=30        # and the room its time limit leaves beyond that
EXTRA=()        # more --set options for every training
PIPE=()         # benchmarks.pipeline's and benchmarks.collection's size
# each step's time limit (seconds): its budget with room for imports and compilation
LIM_MACHINE=60 LIM_DEFAULT_GPU=110 LIM_DEFAULT_CPU=140 LIM_PIPELINE=150 LIM_COLLECTION=90
if [[ "$TINY" == 1 ]]; then
  RECIPE_MIN=0.05 PAPER_MIN=0.05 DEFAULT_ITERS=3 PIPELINE_ITERS=3 TOTAL_S=${TOTAL_S_TINY:-3600}
  SEEDS=2 WORKERS=2 MIN_STEP=0 STARTUP_S=0 SLACK=600
  EXTRA=(--set train.updates_per_iteration=5 --set train.tasks_per_iteration=2)
  PIPE=(--tiny)
  LIM_MACHINE=300 LIM_DEFAULT_GPU=600 LIM_DEFAULT_CPU=600 LIM_PIPELINE=600 LIM_COLLECTION=600
fi
exec > >(tee -a "$OUT/log.txt") 2>&1
export PYTHONPATH="$PWD/src:$PWD${PYTHONPATH:+:$PYTHONPATH}"
export XLA_PYTHON_CLIENT_PREALLOCATE=${XLA_PYTHON_CLIENT_PREALLOCATE:-false}
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR-/tmp/gpu-session-jax-cache}
[[ -z "$JAX_COMPILATION_CACHE_DIR" ]] && unset JAX_COMPILATION_CACHE_DIR
DEADLINE=$((SECONDS + TOTAL_S))
RESERVE=25      # kept for the summary and records.tgz
GRACE=20        # a stopped step's seconds to end (timeout -k)

stamp() { echo "== $(date -u +%H:%M:%S) +${SECONDS}s $*"; }

# limit_for WANTED: WANTED seconds, or the time left before the deadline if less (0: skip)
limit_for() {
  local left=$((DEADLINE - SECONDS - RESERVE - GRACE)) want=$1
  if ((left < MIN_STEP || left <= 0)); then echo 0; elif ((want > left)); then echo "$left"; else echo "$want"; fi
}

# minutes_for MINUTES: MINUTES, or what fits before the deadline beside STARTUP_S
minutes_for() {
  local lim
  lim=$(limit_for $(($(awk -v m="$1" 'BEGIN {print int(m * 60 + 0.999)}') + STARTUP_S)))
  awk -v m="$1" -v l="$lim" -v s="$STARTUP_S" \
    'BEGIN {f = (l - s) / 60; if (f > m) f = m; if (f <= 0) print 0; else printf "%.2f\n", f}'
}

# run_step NAME LIMIT CMD...: CMD under `timeout LIMIT`, its exit status logged
run_step() {
  local name=$1 limit=$2 t0=$SECONDS rc
  shift 2
  if ((limit <= 0)); then stamp "($name) skipped: no time left"; return; fi
  stamp "($name) limit ${limit} s"
  timeout -k "$GRACE" "$limit" "$@"
  rc=$?
  stamp "($name) exit $rc after $((SECONDS - t0)) s"
}

# train_step NAME LIMIT ITERS CMD...: a training into OUT/NAME under `timeout LIMIT`; unless
# FINAL_EVAL=1 it is ended once its training is done: curve.json is written (a minutes run) or
# ITERS iteration rows are logged (ITERS > 0). Its rows are on disk then, so its process group
# (timeout's own: the command and its MPC workers) gets SIGTERM and, 3 s later, SIGKILL; the
# command's own stop handling would finish the final evaluation first.
train_step() {
  local name=$1 limit=$2 iters=$3 dir="$OUT/$1" t0=$SECONDS pid rc rows ended=""
  shift 3
  if ((limit <= 0)); then stamp "($name) skipped: no time left"; return; fi
  rm -rf "$dir"
  stamp "($name) limit ${limit} s: ${*:2}"
  timeout -k "$GRACE" "$limit" "$@" --out "$dir" &
  pid=$!
  if [[ "$FINAL_EVAL" != 1 ]]; then
    while kill -0 "$pid" 2>/dev/null; do
      rows=$(cat "$dir/metrics.jsonl" 2>/dev/null | grep -c collect_s)
      if [[ -f "$dir/curve.json" ]] || ((iters > 0 && rows >= iters)); then
        stamp "($name) training done ($rows iterations): stopping before the final evaluation"
        kill -TERM -- -"$pid" 2>/dev/null
        sleep 3
        kill -KILL -- -"$pid" 2>/dev/null
        ended=" (ended after its training, as planned)"
        break
      fi
      sleep 1
    done
  fi
  wait "$pid" 2>/dev/null
  rc=$?
  stamp "($name) exit $rc after $((SECONDS - t0)) s$ended"
}

stamp "machine"
run_step machine "$(limit_for $LIM_MACHINE)" bash -c '
  { nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null \
      || echo "no nvidia-smi"
    echo "host: $(nproc) cores, $(grep -m1 "model name" /proc/cpuinfo | cut -d: -f2- | sed "s/^ *//")"
    echo "load: $(cat /proc/loadavg)"
    echo "commit: $(git rev-parse HEAD 2>/dev/null || echo unknown)"
    "$0" -c "import importlib.metadata as m, jax
for p in (\"jax\", \"jaxlib\", \"flax\", \"optax\", \"distrax\", \"osqp\", \"numpy\"):
    print(p, m.version(p))
print(\"devices:\", jax.devices())"
  } 2>&1 | tee "$1/machine.txt"' "$PY" "$OUT"

RECIPE=(--preset recipe --eps 0.2 --seeds "$SEEDS" --set mpc.n_workers="$WORKERS"
  --policy-only --no-progress --overwrite "${EXTRA[@]}")
for run in recipe recipe-pipeline; do
  pipe=()
  [[ $run == recipe-pipeline ]] && pipe=(--set train.pipeline=true)
  m=$(minutes_for "$RECIPE_MIN")
  if [[ "$m" == 0 ]]; then stamp "($run) skipped: no time left"; continue; fi
  train_step "$run" "$(limit_for $(($(awk -v m="$m" 'BEGIN {print int(m * 60)}') + STARTUP_S + SLACK)))" \
    0 "$PY" -m experiments.restaurant "${RECIPE[@]}" "${pipe[@]}" --minutes "$m" --eval-minutes "$m"
done

DEFAULT=(--preset default --seeds 1 --iterations "$DEFAULT_ITERS" --no-progress --overwrite
  "${EXTRA[@]}")
train_step default-gpu "$(limit_for $LIM_DEFAULT_GPU)" "$DEFAULT_ITERS" \
  "$PY" -m experiments.restaurant "${DEFAULT[@]}"
train_step default-cpu "$(limit_for $LIM_DEFAULT_CPU)" "$DEFAULT_ITERS" \
  env JAX_PLATFORMS=cpu "$PY" -m experiments.restaurant "${DEFAULT[@]}"

m=$(minutes_for "$PAPER_MIN")
if [[ "$m" == 0 ]]; then
  stamp "(paper) skipped: no time left"
else
  train_step paper "$(limit_for $(($(awk -v m="$m" 'BEGIN {print int(m * 60)}') + STARTUP_S + SLACK)))" \
    0 "$PY" -m experiments.restaurant --preset paper --eps 0.2 --seeds 1 --minutes "$m" \
    --eval-minutes "$m" --policy-only --no-progress --overwrite "${EXTRA[@]}"
fi

run_step pipeline "$(limit_for $LIM_PIPELINE)" \
  "$PY" -m benchmarks.pipeline "${PIPE[@]}" --iterations "$PIPELINE_ITERS" --out "$OUT"
run_step collection "$(limit_for $LIM_COLLECTION)" \
  "$PY" -m benchmarks.collection "${PIPE[@]}" --seeds 8 --out "$OUT"

stamp "summary"
$PY -m benchmarks.gpu_summary "$OUT" | tee "$OUT/summary.txt"
(cd "$OUT" && find . -path ./records.tgz -prune -o -type f \
  \( -name '*.json' -o -name '*.jsonl' -o -name '*.txt' \) -print | sort |
  tar -czf records.tgz -T -)
stamp "done in ${SECONDS} s: $OUT/summary.txt, $OUT/records.tgz ($(du -h "$OUT/records.tgz" | cut -f1))"
