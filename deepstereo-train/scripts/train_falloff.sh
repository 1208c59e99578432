#!/usr/bin/env bash
# Issue 17's fine-tuning run: the `nviews` preset with its view falloff (config
# pool.falloff: sources beyond the nearest 4 weigh (d_ref / d)^8, view_weights.rs),
# started from the weights of the previous default (nviews-real at step 8600, copied into
# the run as init.safetensors) and trained on the same scenes and options as that run
# (train_default.sh), views 2-10 per batch, Adam 2e-4 held to step 200, then a cosine to
# 2e-5 at step 2200 (started as cosine:200-3000, shortened at step 1582 to fit the session).
# Continues from its committed checkpoint when there is one.
# Run from the repository root: bash deepstereo-train/scripts/train_falloff.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=deepstereo-train/runs/nviews-falloff
STEPS="${1:-2200}"
SCHEDULE="${2:-cosine:200-2200}"
# shellcheck source=deepstereo-train/scripts/default_data.sh
source deepstereo-train/scripts/default_data.sh
RESUME=()
if [ -f "$OUT/checkpoint.safetensors" ]; then RESUME=(--resume); fi
cargo build --release -p deepstereo-train
exec nice -n 19 target/release/deepstereo train --config nviews --views 2-10 \
  --init "$OUT/init.safetensors" \
  --data "${TRAIN[@]}" --synthetic 200 --synth-size 240x180 --synth-views 12 \
  --synthetic-percent 40 --augment --val-data "${VAL[@]}" --val-scenes 8 --val-batches 8 \
  --steps "$STEPS" --batch 8 --optimizer adam --lr 2e-4 --seed 2 \
  --lr-schedule "$SCHEDULE" --lr-final 0.1 \
  --checkpoint-every 100 --validate-every 250 --log-every 20 --no-progress \
  --out "$OUT" "${RESUME[@]}"
