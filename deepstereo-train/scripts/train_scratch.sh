#!/usr/bin/env bash
# Session 12's experiment: the embedded model's architecture and proximity weights
# (runs/nviews-prox/config.json: pool.falloff 1:2) trained from scratch, instead of
# nviews-real's weights (trained without them) fine-tuned with them. train_default.sh's
# scenes, sampling and seed (1), Adam 1e-3 to step 3000 (nviews-real's validation was flat
# from ~1400 at that rate), then a cosine to 5e-5 at step 5500 (44k samples, against
# nviews-real's 68.8k plus nviews-prox's 16k). Continues from its committed checkpoint
# when there is one. Run from the repository root:
# bash deepstereo-train/scripts/train_scratch.sh [STEPS] [LR_SCHEDULE]
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-scratch}"
STEPS="${1:-5500}"
SCHEDULE="${2:-cosine:3000-5500}"
mkdir -p "$OUT"
[ -f "$OUT/config.json" ] || cp deepstereo-train/runs/nviews-prox/config.json "$OUT/config.json"
# shellcheck source=deepstereo-train/scripts/default_data.sh
source deepstereo-train/scripts/default_data.sh
cargo build --release -p deepstereo-train
exec nice -n 19 target/release/deepstereo train --config "$OUT/config.json" "${SAMPLING[@]}" \
  --steps "$STEPS" --batch 8 --optimizer adam --lr 1e-3 --seed 1 \
  --lr-schedule "$SCHEDULE" --lr-final 0.05 \
  --checkpoint-every 100 --validate-every 250 --log-every 20 --no-progress \
  --out "$OUT" "${RESUME[@]}"
