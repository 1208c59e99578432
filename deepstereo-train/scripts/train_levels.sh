#!/usr/bin/env bash
# Session 14's experiment (issue 20: is the depth selection short of spatial context?):
# the shipped weights (runs/nviews-prox at step 2000) with a fourth resolution level (1/8)
# in the selection tower, added without changing what they compute (add_levels.py: the
# new level's convolutions He-initialised, the first merge convolution's weights on its
# channels zero; the render time is unchanged within noise), then fine-tuned with
# finetune.sh's options at Adam 4e-4 (the new level starts from scratch), held to step
# 100, a cosine to 4e-5 at step 1500. Continues from its committed checkpoint when there
# is one. Needs the test command's venv (numpy, safetensors) the first time.
# Run from the repository root: bash deepstereo-train/scripts/train_levels.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-l4}"
LEVELS="${LEVELS:-4}"
PY="${PY:-.venv/bin/python}"
mkdir -p "$OUT"
if [ ! -f "$OUT/init.safetensors" ]; then
  "$PY" deepstereo-train/scripts/add_levels.py deepstereo-train/runs/nviews-prox/model.safetensors \
    "$OUT/init.safetensors" "$OUT/config.json" "$LEVELS"
fi
LR=4e-4 OUT="$OUT" INIT="$OUT/init.safetensors" CONFIG="$OUT/config.json" \
  exec bash deepstereo-train/scripts/finetune.sh "${1:-1500}" "${2:-cosine:100-1500}"
