#!/usr/bin/env bash
# DrawAnything-Real at CPU scale: BPP and Goal-Image trained on scripted demonstrations of procedural drawings (and a
# person's phone recordings of more), evaluated on unseen human-made drawings at new random canvas placements (one
# demonstration of each as the prompt: the arm's, a phone's, or both in turn), scored by DrawAnything's Chamfer from
# the simulator's ink and from a photo of the board.
#
#   bash bench/draw3d_cpu.sh    # TASKS=500 DEMOS=3 PHONE=40 STEPS=12000 HUMAN=20 ROLLOUTS=2 OBS=canvas PROMPTS=both
#   TASKS=60 PHONE=0 STEPS=6000 PROMPTS=arm bash bench/draw3d_cpu.sh     # a smaller run, the arm's prompts only
#   OBS=state PHONE=0 PROMPTS=arm METHODS=bpp bash bench/draw3d_cpu.sh  # one method, in the robot's base frame
#
# HUMAN of the 50 human-made drawings are evaluated, spread evenly. One thread per process; the methods train and
# evaluate side by side (2 cores), generation runs on WORKERS processes.
#
# PHONE=K adds K more procedural drawings x DEMOS, drawn by a person with an iPhUMI phone (synthetic recordings on the
# marked canvas, processed with --canvas and converted with bpp draw3d from-iphumi), to the training data (OBS=canvas:
# the phone has no robot base frame). PROMPTS=phone prompts with phone recordings of the human-made drawings instead
# of the arm's demonstrations of them (PROMPTS=both: each policy is evaluated with both).
set -euo pipefail
TASKS=${TASKS:-500} DEMOS=${DEMOS:-3} STEPS=${STEPS:-12000} HUMAN=${HUMAN:-20} ROLLOUTS=${ROLLOUTS:-2}
OBS=${OBS:-canvas} METHODS=${METHODS:-bpp goal_image} WORKERS=${WORKERS:-2} PHONE=${PHONE:-40} PROMPTS=${PROMPTS:-both}
if [ "$PHONE" -gt 0 ] && [ "$OBS" != canvas ]; then
  echo "PHONE=$PHONE needs OBS=canvas (a phone has no robot base frame): give PHONE=0 PROMPTS=arm" >&2; exit 2
fi
with_phone=""; [ "$PHONE" -gt 0 ] && with_phone="-phone$PHONE"
DATA=${DATA:-data/draw3d} RUNS=${RUNS:-runs/draw3d-cpu-$OBS-$TASKS$with_phone}
export OMP_NUM_THREADS=1 MUJOCO_GL=${MUJOCO_GL:-egl}
BPP=${BPP:-bpp}
train="$DATA/procedural-${TASKS}x${DEMOS}.zarr"
human="$DATA/human.zarr"  # DrawAnything's 50 human-made drawings, one demonstration each (the prompts)
[ -d "$train" ] || $BPP draw3d generate --preset cpu --num-tasks "$TASKS" --demos-per-task "$DEMOS" --workers "$WORKERS" --out "$train"
[ -d "$human" ] || $BPP draw3d generate --preset cpu --source human --demos-per-task 1 --workers "$WORKERS" --out "$human"
phone() {  # phone NAME SYNTH_OPTIONS...: synthetic iPhUMI drawings on the marked canvas -> $DATA/phone-NAME.zarr
  local name=$1; shift
  [ -d "$DATA/phone-$name.zarr" ] && return
  rm -rf "$DATA/phone-$name-export"
  $BPP iphumi synth "$DATA/phone-$name-export" --canvas --main-size 320 240 "$@"
  $BPP iphumi process "$DATA/phone-$name-export" --canvas --fps 20 --workers "$WORKERS" --overwrite \
    --out "$DATA/phone-$name-processed.zarr"
  $BPP draw3d from-iphumi "$DATA/phone-$name-processed.zarr" --out "$DATA/phone-$name.zarr"
}
if [ "$PHONE" -gt 0 ]; then
  phone "procedural-${PHONE}x${DEMOS}" --tasks "$PHONE" --demonstrations $((PHONE * DEMOS)) --seed 11
  mixed="$DATA/procedural-${TASKS}x${DEMOS}-phone-${PHONE}x${DEMOS}.zarr"
  [ -d "$mixed" ] || $BPP store merge "$train" "$DATA/phone-procedural-${PHONE}x${DEMOS}.zarr" --out "$mixed"
  train=$mixed
fi
prompts=()
case $PROMPTS in
  arm) prompts=(arm) ;;
  phone) prompts=(phone) ;;
  both) prompts=(arm phone) ;;
  *) echo "PROMPTS must be arm, phone or both" >&2; exit 2 ;;
esac
[[ " ${prompts[*]} " == *" phone "* ]] && phone human --drawings human --tasks 50 --demonstrations 50 --seed 12
for method in $METHODS; do
  $BPP train --data "$train" --out "$RUNS/$method" --method "$method" --preset cpu --obs "$OBS" --steps "$STEPS" \
    --threads 1 --workers 0 &
done
wait
for prompt in "${prompts[@]}"; do
  tasks=$human suffix=""
  [ "$prompt" = phone ] && tasks="$DATA/phone-human.zarr" suffix="-phone"
  for method in $METHODS; do
    $BPP eval "$RUNS/$method" --tasks "$tasks" --num-tasks "$HUMAN" --rollouts "$ROLLOUTS" --workers 1 --videos 1 \
      --out "$RUNS/$method-eval$suffix" &
  done
  wait
done
