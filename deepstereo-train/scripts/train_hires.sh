#!/usr/bin/env bash
# Session 12's experiment: the eval's procedural scenes are 504x378 and the real ones
# 250-521 pixels wide, while every run so far trained on procedural scenes of 240x180
# (disparities in pixels half the eval's). The shipped weights (runs/nviews-prox at step
# 2000) fine-tuned with the procedural scenes rendered at 360x270 (finetune.sh's options
# otherwise: same real scenes, 2-10 views, augmentation, Adam 2e-4 held to step 100, a
# cosine to 2e-5 at step 1500, seed 2). Continues from its committed checkpoint when there
# is one. Run from the repository root: bash deepstereo-train/scripts/train_hires.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
OUT="${OUT:-deepstereo-train/runs/nviews-hires}"
INIT="${INIT:-deepstereo-train/runs/nviews-prox/model.safetensors}"
mkdir -p "$OUT"
[ -f "$OUT/config.json" ] || cp deepstereo-train/runs/nviews-prox/config.json "$OUT/config.json"
SYNTH_SIZE=360x270 OUT="$OUT" INIT="$INIT" CONFIG="$OUT/config.json" \
  exec bash "$(dirname "$0")/finetune.sh" "${1:-1500}" "${2:-cosine:100-1500}"
