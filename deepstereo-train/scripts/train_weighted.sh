#!/usr/bin/env bash
# Session 14's experiment (issue 20: the issue's "sampler that weights scenes"): the
# shipped weights (runs/nviews-prox at step 2000) fine-tuned with finetune.sh's options
# and `train --scene-weights`: the four 360-degree object captures of the training set
# (blowtorch, maryrose, milk, plant; by the data README's descriptions, the kind of
# capture four of the six evaluation scenes are) drawn 3 times as often as each other
# real scene. Adam 2e-4, held to step 100, a cosine to 2e-5 at step 1500. Continues from
# its committed checkpoint when there is one.
# Run from the repository root: bash deepstereo-train/scripts/train_weighted.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-weighted}"
mkdir -p "$OUT"
[ -f "$OUT/config.json" ] || cp deepstereo-train/runs/nviews-prox/config.json "$OUT/config.json"
SCENE_WEIGHTS="${SCENE_WEIGHTS:-blowtorch=3,maryrose=3,milk=3,plant=3}" OUT="$OUT" \
  INIT=deepstereo-train/runs/nviews-prox/model.safetensors CONFIG="$OUT/config.json" \
  exec bash deepstereo-train/scripts/finetune.sh "${1:-1500}" "${2:-cosine:100-1500}"
