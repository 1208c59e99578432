#!/usr/bin/env bash
# Issue 20's fine-tuning run: the `nviews` architecture with a soft proximity falloff in
# its config (runs/nviews-prox/config.json: pool.falloff 1:2, every source but the
# nearest weighs (d_1 / d_v)^2 in alpha, deepstereo-core/src/view_weights.rs), so the model
# learns from which sources are closest to the target (a coinciding source takes over;
# the far side of a ring counts less). Started from the previous default's weights
# (nviews-real at step 8600, runs/nviews-falloff/init.safetensors), same scenes and
# options as train_falloff.sh: views 2-10 per batch, Adam 2e-4 held to step 200, then a
# cosine to 2e-5 at step 2000. Continues from its committed checkpoint when there is one.
# A continuation from its weights (a fresh optimizer and a new cosine) runs with
# OUT=deepstereo-train/runs/nviews-prox2 INIT=deepstereo-train/runs/nviews-prox/model.safetensors
# (that run's config.json is a copy of this one's).
# Run from the repository root: bash deepstereo-train/scripts/train_prox.sh [STEPS] [LR_SCHEDULE]
# (the options: finetune.sh).
set -euo pipefail
OUT="${OUT:-deepstereo-train/runs/nviews-prox}"
INIT="${INIT:-deepstereo-train/runs/nviews-falloff/init.safetensors}"
OUT="$OUT" INIT="$INIT" CONFIG="$OUT/config.json" \
  exec bash "$(dirname "$0")/finetune.sh" "${1:-2000}" "${2:-cosine:200-2000}"
