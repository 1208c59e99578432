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
HERE="$(cd "$(dirname "$0")" && pwd)"
cd "$HERE/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-scratch}"
mkdir -p "$OUT"
[ -f "$OUT/config.json" ] || cp deepstereo-train/runs/nviews-prox/config.json "$OUT/config.json"
# train_default.sh's command with this run's directory (and config), schedule and
# validation interval.
OUT="$OUT" VALIDATE_EVERY=250 \
  exec bash "$HERE/train_default.sh" "${1:-5500}" "${2:-cosine:3000-5500}"
