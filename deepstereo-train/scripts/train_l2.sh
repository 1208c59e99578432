#!/usr/bin/env bash
# Session 12's experiment: does a squared-error loss (PSNR's own) beat L1 on held-out
# views? The shipped weights (runs/nviews-prox at step 2000) fine-tuned with `--loss l2`
# (finetune.sh's options otherwise: same scenes, 2-10 views, augmentation, Adam 2e-4 held
# to step 100, a cosine to 2e-5 at step 1200, seed 2). Continues from its committed
# checkpoint when there is one.
# Run from the repository root: bash deepstereo-train/scripts/train_l2.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
OUT="${OUT:-deepstereo-train/runs/nviews-l2}"
INIT="${INIT:-deepstereo-train/runs/nviews-prox/model.safetensors}"
mkdir -p "$OUT"
[ -f "$OUT/config.json" ] || cp deepstereo-train/runs/nviews-prox/config.json "$OUT/config.json"
LOSS=l2 OUT="$OUT" INIT="$INIT" CONFIG="$OUT/config.json" \
  exec bash "$(dirname "$0")/finetune.sh" "${1:-1200}" "${2:-cosine:100-1200}"
