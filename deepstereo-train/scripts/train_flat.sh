#!/usr/bin/env bash
# Session 13's experiment (issue 20: "a sampler that skips textureless tiles"): the shipped
# weights (runs/nviews-prox at step 2000) fine-tuned with `train --skip-flat 0.02` (a
# training tile whose target luminance varies by less than 0.02 standard deviation is
# redrawn, up to 8 times), finetune.sh's recipe otherwise (Adam 2e-4 held to step 100, a
# cosine to 2e-5 at step 1500, seed 2). Continues from its committed checkpoint when there
# is one. Run from the repository root: bash deepstereo-train/scripts/train_flat.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-flat}"
mkdir -p "$OUT"
[ -f "$OUT/config.json" ] || cp deepstereo-train/runs/nviews-prox/config.json "$OUT/config.json"
SKIP_FLAT=0.02 OUT="$OUT" INIT=deepstereo-train/runs/nviews-prox/model.safetensors \
  CONFIG="$OUT/config.json" exec bash deepstereo-train/scripts/finetune.sh "${1:-1500}" "${2:-cosine:100-1500}"
