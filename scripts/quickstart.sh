#!/usr/bin/env bash
# The README's first command: install everything, then run the main job on the `tiny` preset (CPU, minutes):
#   1. list the tasks and render a few frames of each family,
#   2. collect a small medium-replay dataset of walker_uphill with the DreamerV2 collector,
#   3. train CoWorld (source walker_walk -> target walker_uphill) on it,
#   4. evaluate the trained target agent (returns, value check, video).
# Everything lands under out/quickstart (datasets, runs, frames, video). Rerunning resumes or reuses it.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export MUJOCO_GL=${MUJOCO_GL:-egl}
coworld=.venv/bin/coworld
out=${OUT_DIR:-out/quickstart}
mkdir -p "$out"

$coworld tasks
for task in walker_uphill cheetah_nopaw mw_door_close robodesk_push_button toy_reach; do
  $coworld render --task "$task" --frames 3 --out "$out/frames/$task"
done

dataset="$out/walker_uphill-medium_replay.h5"
if [ ! -f "$dataset" ] || ! $coworld dataset verify "$dataset" >/dev/null 2>&1; then
  $coworld collect --task walker_uphill --preset tiny --max-steps 2000 --out "$dataset" --resume
fi
$coworld dataset info "$dataset"

run="$out/runs/coworld-walker_walk-walker_uphill"
$coworld train --source walker_walk --target walker_uphill --dataset "$dataset" --preset tiny --logdir "$run"
$coworld eval --ckpt "$run" --episodes 2 --workers 2 --video "$out/eval.mp4" --force
echo "quickstart: done; see $out"
