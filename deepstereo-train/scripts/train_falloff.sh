#!/usr/bin/env bash
# Issue 17's fine-tuning run: the `nviews` preset with its view falloff (config
# pool.falloff: sources beyond the nearest 4 weigh (d_ref / d)^8, view_weights.rs),
# started from the weights of the previous default (nviews-real at step 8600, copied into
# the run as init.safetensors) and trained on the same scenes and options as that run
# (train_default.sh), views 2-10 per batch, Adam 2e-4 held to step 200, then a cosine to
# 2e-5 at step 2200 (started as cosine:200-3000, shortened at step 1582 to fit the session).
# Continues from its committed checkpoint when there is one.
# Run from the repository root: bash deepstereo-train/scripts/train_falloff.sh [STEPS] [LR_SCHEDULE]
# (the options: finetune.sh).
set -euo pipefail
OUT=deepstereo-train/runs/nviews-falloff INIT=deepstereo-train/runs/nviews-falloff/init.safetensors \
  CONFIG=nviews exec bash "$(dirname "$0")/finetune.sh" "${1:-2200}" "${2:-cosine:200-2200}"
