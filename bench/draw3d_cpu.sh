#!/usr/bin/env bash
# DrawAnything-Real at CPU scale, state-only: BPP and Goal-Image trained on scripted demonstrations of procedural
# drawings, evaluated on unseen human-made drawings at new random canvas placements (one demonstration of each as the
# prompt), scored by DrawAnything's Chamfer from the simulator's ink and from a photo of the board.
#
#   bash bench/draw3d_cpu.sh            # TASKS=60 DEMOS=3 STEPS=3000 HUMAN=10 ROLLOUTS=2 OBS=state by default
#   OBS=canvas METHODS=bpp WORKERS=1 bash bench/draw3d_cpu.sh      # one method, in the canvas's frame, on one core
#
# HUMAN of the 50 human-made drawings are evaluated, spread evenly. One thread per process; the methods train and
# evaluate side by side (2 cores), generation runs on WORKERS processes.
set -euo pipefail
TASKS=${TASKS:-60} DEMOS=${DEMOS:-3} STEPS=${STEPS:-3000} HUMAN=${HUMAN:-10} ROLLOUTS=${ROLLOUTS:-2}
OBS=${OBS:-state} METHODS=${METHODS:-bpp goal_image} WORKERS=${WORKERS:-2}
DATA=${DATA:-data/draw3d} RUNS=${RUNS:-runs/draw3d-cpu-$OBS}
export OMP_NUM_THREADS=1 MUJOCO_GL=${MUJOCO_GL:-egl}
BPP=${BPP:-bpp}
train="$DATA/procedural-${TASKS}x${DEMOS}.zarr"
human="$DATA/human.zarr"  # DrawAnything's 50 human-made drawings, one demonstration each (the prompts)
[ -d "$train" ] || $BPP draw3d generate --preset cpu --num-tasks "$TASKS" --demos-per-task "$DEMOS" --workers "$WORKERS" --out "$train"
[ -d "$human" ] || $BPP draw3d generate --preset cpu --source human --demos-per-task 1 --workers "$WORKERS" --out "$human"
for method in $METHODS; do
  $BPP train --data "$train" --out "$RUNS/$method" --method "$method" --preset cpu --obs "$OBS" --steps "$STEPS" \
    --threads 1 --workers 0 &
done
wait
for method in $METHODS; do
  $BPP eval "$RUNS/$method" --tasks "$human" --num-tasks "$HUMAN" --rollouts "$ROLLOUTS" --workers 1 --videos 1 \
    --out "$RUNS/$method-eval" &
done
wait
