#!/usr/bin/env bash
# Session 13's experiment (issue 20: wide baselines): the shipped weights (runs/nviews-prox
# at step 2000) fine-tuned with sparser sources, `--view-stride 1-3` (per sample the
# nearest views, every 2nd or every 3rd nearest: the baselines of a capture with a half
# or a third of its views, nearer those of moldgoldcape and ethiopianHead), finetune.sh's
# options otherwise (Adam 2e-4 held to step 100, a cosine to 2e-5 at step 1500, seed 2).
# Continues from its committed checkpoint when there is one.
# Run from the repository root: bash deepstereo-train/scripts/train_stride.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-stride}"
mkdir -p "$OUT"
[ -f "$OUT/config.json" ] || cp deepstereo-train/runs/nviews-prox/config.json "$OUT/config.json"
VIEW_STRIDE=1-3 OUT="$OUT" INIT=deepstereo-train/runs/nviews-prox/model.safetensors \
  CONFIG="$OUT/config.json" exec bash deepstereo-train/scripts/finetune.sh "${1:-1500}" "${2:-cosine:100-1500}"
