#!/usr/bin/env bash
# Session 13's experiment (issue 20: is the architecture short of capacity?): the shipped
# weights (runs/nviews-prox at step 2000) widened without changing what they compute
# (widen.py: encoder 6 -> 12 channels, select level convs 12 -> 18, first select merge
# conv 12 -> 18, colour conv 12 -> 18, blend 6 -> 12; about 2.4x the render time, so not
# shippable under issue 20's time limit as it is), then fine-tuned with finetune.sh's
# options at Adam 4e-4 (the new channels start from scratch), held to step 100, a cosine
# to 4e-5 at step 1500. Continues from its committed checkpoint when there is one. Needs
# the test command's venv (numpy, safetensors) the first time.
# Run from the repository root: bash deepstereo-train/scripts/train_wide.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-wide}"
PY="${PY:-.venv/bin/python}"
mkdir -p "$OUT"
if [ ! -f "$OUT/init.safetensors" ]; then
  "$PY" deepstereo-train/scripts/widen.py deepstereo-train/runs/nviews-prox/model.safetensors \
    "$OUT/init.safetensors" "$OUT/config.json" 12 18 18 18 12
fi
LR=4e-4 OUT="$OUT" INIT="$OUT/init.safetensors" CONFIG="$OUT/config.json" \
  exec bash deepstereo-train/scripts/finetune.sh "${1:-1500}" "${2:-cosine:100-1500}"
