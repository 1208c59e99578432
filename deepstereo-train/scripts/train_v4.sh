#!/usr/bin/env bash
# Session 11's experiment: does training at the eval's and the default's view count help?
# The shipped weights (runs/nviews-prox at step 2000) fine-tuned with exactly 4 source
# views per batch (finetune.sh's options otherwise: same scenes, augmentation, Adam 2e-4
# held to step 100, a cosine to 2e-5 at step 1500, seed 2, so its validation compares with
# nviews-prox's). Continues from its committed checkpoint when there is one.
# Run from the repository root: bash deepstereo-train/scripts/train_v4.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
OUT="${OUT:-deepstereo-train/runs/nviews-v4}"
INIT="${INIT:-deepstereo-train/runs/nviews-prox/model.safetensors}"
VIEW_RANGE=4 OUT="$OUT" INIT="$INIT" CONFIG="$OUT/config.json" \
  exec bash "$(dirname "$0")/finetune.sh" "${1:-1500}" "${2:-cosine:100-1500}"
