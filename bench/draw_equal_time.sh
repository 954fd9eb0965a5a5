#!/usr/bin/env bash
# DrawAnything's BPP against ICRT at equal training wall time, one seed: both train side by side, one thread and one
# core each, on the main job's store (`board` observations, the `cpu` size, 8 prompts a step; BPP 64 windows a step
# from zero noise, ICRT 16 whole demonstrations), for step counts that take about the same time. Then, on each
# method's own lane: every checkpoint on the procedural validation split (bench/draw_curves.py), the step with the
# lowest validation mean chosen (the rule is fixed before any unseen drawing is seen), the 50 unseen human-made
# drawings x 8 rollouts at the schedule's end and at the chosen step, and the 20 training drawings x 8 at the end.
#
#   bash bench/draw_equal_time.sh 1                        # seed 1: BPP 32,000 steps, ICRT 18,000 (about 80 min each)
#   BPP_STEPS=8000 ICRT_STEPS=4500 VAL_TASKS=20 bash bench/draw_equal_time.sh 0   # a quarter of it
#   BPP_STEPS=16 ICRT_STEPS=18 VAL_TASKS=2 HUMAN=2 ROLLOUTS=1 RUNS=/tmp/r OUT=/tmp/o \
#     bash bench/draw_equal_time.sh 0                     # a check that it all runs (3 minutes)
#
# Other methods take the same lanes: METHODS names them, each with its steps (GOAL_IMAGE_STEPS for goal_image); only
# BPP samples from zero noise, the others as trained (each method's choice on the validation split, BENCHMARKS.md).
# BPP_NOISE sets BPP's (1: as trained, the validation split's choice on `board-image`).
# Two seeds of one method side by side, one lane each:
#   METHODS=goal_image GOAL_IMAGE_STEPS=28000 bash bench/draw_equal_time.sh 0 &
#   METHODS=goal_image GOAL_IMAGE_STEPS=28000 bash bench/draw_equal_time.sh 1
# OBS picks the observation (`board` unless set); a `board-image` step costs more (BENCHMARKS.md), so fewer fill the
# same time:
#   OBS=board-image BPP_STEPS=17600 ICRT_STEPS=10350 BPP_NOISE=1 RUNS=runs/long-image OUT=outputs/long-image \
#     bash bench/draw_equal_time.sh 0
# and Goal-Image's two seeds side by side (its `board-image` step reads no prompt's frames: more steps fill the time):
#   OBS=board-image METHODS=goal_image GOAL_IMAGE_STEPS=26400 RUNS=runs/long-image OUT=outputs/long-image \
#     bash bench/draw_equal_time.sh 0 &
# TRAIN_FLAGS adds training flags to every lane, e.g. the image encoder's pool over a 2x2 grid of the view:
#   OBS=board-view BPP_STEPS=12000 ICRT_STEPS=5000 BPP_NOISE=1 TRAIN_FLAGS="--model.obs.image-pool-grid 2" \
#     RUNS=runs/grid OUT=outputs/grid bash bench/draw_equal_time.sh 0
#
# Stopped part way, the same command continues each lane from its last checkpoint and reuses the evaluations
# already made.
#
# Compare two seeds or more afterwards, drawing by drawing:
#   python bench/paired.py OUT/human/icrt-s0-18000/results.json,OUT/human/icrt-s1-18000/results.json \
#       OUT/human/bpp-s0-32000/results.json,OUT/human/bpp-s1-32000/results.json
set -euo pipefail
SEED=${1:?usage: bash bench/draw_equal_time.sh SEED}
BPP_STEPS=${BPP_STEPS:-32000} ICRT_STEPS=${ICRT_STEPS:-18000}
VAL_TASKS=${VAL_TASKS:-50} HUMAN=${HUMAN:-50} ROLLOUTS=${ROLLOUTS:-8}
DATA=${DATA:-data/draw/train-500.zarr} RUNS=${RUNS:-runs/long} OUT=${OUT:-outputs/long} BPP=${BPP:-bpp}
PYTHON=${PYTHON:-python} BPP_NOISE=${BPP_NOISE:-0}
export OMP_NUM_THREADS=1
[ -d "$DATA" ] || $BPP draw generate --preset cpu --out "$DATA" --workers 2
mkdir -p "$OUT/logs"
METHODS=${METHODS:-bpp icrt} OBS=${OBS:-board}
common=(--data "$DATA" --preset cpu --obs "$OBS" --tasks-per-batch 8 --threads 1 --workers 0 --keep-checkpoints 50
  --seed "$SEED")
read -ra extra <<< "${TRAIN_FLAGS:-}"
common+=("${extra[@]}")

steps() {  # steps METHOD: the method's step count (BPP_STEPS, ICRT_STEPS, GOAL_IMAGE_STEPS, ...)
  local name="${1^^}_STEPS"
  echo "${!name:?set $name}"
}

train() {  # train METHOD: one lane's training; BPP samples from BPP_NOISE, ICRT takes 16 whole demonstrations a step.
  # A lane stopped part way (killed, or its machine shut down) continues from its last checkpoint when the same
  # command runs again; its log keeps both parts.
  local method=$1 total run="$RUNS/$1-s$SEED" log="$OUT/logs/train-$1-s$SEED.log"
  total=$(steps "$method")
  local flags=(--save-every $((total / 8)))
  [ "$method" = bpp ] && flags+=(--model.diffusion.noise-scale "$BPP_NOISE")
  [ "$method" = icrt ] && flags=(--save-every $((total / 9)) --batch-size 16)
  if [ -f "$run/checkpoints/last" ]; then flags+=(--resume); else : > "$log"; fi
  $BPP train --method "$method" "${common[@]}" --out "$run" --steps "$total" "${flags[@]}" >> "$log" 2>&1
}

lanes=()
for method in $METHODS; do
  train "$method" &
  lanes+=($!)
done
for pid in "${lanes[@]}"; do wait "$pid"; done  # any failing stops here (its log is in $OUT/logs)
echo "trained: $METHODS, seed $SEED, in $RUNS"

lane() {  # lane METHOD END: validation, the chosen step, then the unseen and training drawings
  local method=$1 end=$2 run="$RUNS/$1-s$SEED" val="$OUT/val-$1-s$SEED" chosen step
  $PYTHON bench/draw_curves.py "$run" --num-tasks "$VAL_TASKS" --rollouts 2 --out "$val" \
    > "$OUT/logs/val-$method-s$SEED.log" 2>&1
  chosen=$($PYTHON -c "import json, sys; curve = next(iter(json.load(open(sys.argv[1])).values()));
print(min(curve, key=lambda point: point['val'])['step'])" "$val/results.json")
  echo "$method, seed $SEED: validation chose step $chosen of $end"
  for step in $(printf '%s\n' "$end" "$chosen" | sort -u); do  # bpp eval reuses results it already made
    $BPP eval "$run/checkpoints/step_$(printf %08d "$step")" --tasks human --num-tasks "$HUMAN" \
      --rollouts "$ROLLOUTS" --workers 1 --videos 0 --out "$OUT/human/$method-s$SEED-$step" \
      > "$OUT/logs/human-$method-s$SEED-$step.log" 2>&1
  done
  $BPP eval "$run/checkpoints/step_$(printf %08d "$end")" --tasks train --num-tasks 20 --rollouts "$ROLLOUTS" \
    --workers 1 --videos 0 --out "$OUT/train/$method-s$SEED-$end" > "$OUT/logs/train-eval-$method-s$SEED.log" 2>&1
}
lanes=()
for method in $METHODS; do
  lane "$method" "$(steps "$method")" &
  lanes+=($!)
done
for pid in "${lanes[@]}"; do wait "$pid"; done
echo "unseen drawings: $OUT/human/*-s$SEED-*/results.md"
