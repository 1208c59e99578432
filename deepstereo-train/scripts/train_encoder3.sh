#!/usr/bin/env bash
# Session 13's experiment (issue 20: does the per-view encoder need spatial context?): the
# shipped weights (runs/nviews-prox at step 2000) with their first view-encoder layer
# turned from 1x1 into 3x3 (spatial_encoder.py: the old weights at the centre tap, so the
# start renders what the shipped weights do; the encoder zero-pads), fine-tuned with
# finetune.sh's options at Adam 2e-4, held to step 100, a cosine to 2e-5 at step 1500.
# Continues from its committed checkpoint when there is one. Needs the test command's
# venv (numpy, safetensors) the first time, and the zero-padded KxK encoder, which is not
# in the library (zero padding breaks the tile geometry's exactness: tiles rendered apart
# would differ at their borders; measured no better, README): apply it first with
# `git apply deepstereo-train/runs/nviews-enc3/encoder3.patch` (without it the config is
# refused: "encoder and blend layers must be 1x1"), and the same to evaluate the run.
# Run from the repository root: bash deepstereo-train/scripts/train_encoder3.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-enc3}"
PY="${PY:-.venv/bin/python}"
mkdir -p "$OUT"
if [ ! -f "$OUT/init.safetensors" ]; then
  "$PY" deepstereo-train/scripts/spatial_encoder.py deepstereo-train/runs/nviews-prox/model.safetensors \
    "$OUT/init.safetensors" "$OUT/config.json" 3
fi
OUT="$OUT" INIT="$OUT/init.safetensors" CONFIG="$OUT/config.json" \
  exec bash deepstereo-train/scripts/finetune.sh "${1:-1500}" "${2:-cosine:100-1500}"
