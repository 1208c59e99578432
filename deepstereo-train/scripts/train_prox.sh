#!/usr/bin/env bash
# Issue 20's fine-tuning run: the `nviews` architecture with a soft proximity falloff in
# its config (runs/nviews-prox/config.json: pool.falloff 1:2, every source but the
# nearest weighs (d_1 / d_v)^2 in alpha, deepstereo-core/src/view_weights.rs), so the model
# learns from which sources are closest to the target (a coinciding source takes over;
# the far side of a ring counts less). Started from the shipped default's weights
# (nviews-real at step 8600, runs/nviews-falloff/init.safetensors), same scenes and
# options as train_falloff.sh: views 2-10 per batch, Adam 2e-4 held to step 200, then a
# cosine to 2e-5 at step 2000. Continues from its committed checkpoint when there is one.
# A continuation from its weights (a fresh optimizer and a new cosine) runs with
# OUT=deepstereo-train/runs/nviews-prox2 INIT=deepstereo-train/runs/nviews-prox/model.safetensors
# (that run's config.json is a copy of this one's).
# Run from the repository root: bash deepstereo-train/scripts/train_prox.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-prox}"
INIT="${INIT:-deepstereo-train/runs/nviews-falloff/init.safetensors}"
STEPS="${1:-2000}"
SCHEDULE="${2:-cosine:200-2000}"
# shellcheck source=deepstereo-train/scripts/default_data.sh
source deepstereo-train/scripts/default_data.sh
RESUME=()
if [ -f "$OUT/checkpoint.safetensors" ]; then RESUME=(--resume); fi
cargo build --release -p deepstereo-train
exec nice -n 19 target/release/deepstereo train --config "$OUT/config.json" --views 2-10 \
  --init "$INIT" \
  --data "${TRAIN[@]}" --synthetic 200 --synth-size 240x180 --synth-views 12 \
  --synthetic-percent 40 --augment --val-data "${VAL[@]}" --val-scenes 8 --val-batches 8 \
  --steps "$STEPS" --batch 8 --optimizer adam --lr 2e-4 --seed 2 \
  --lr-schedule "$SCHEDULE" --lr-final 0.1 \
  --checkpoint-every 100 --validate-every 250 --log-every 20 --no-progress \
  --out "$OUT" "${RESUME[@]}"
