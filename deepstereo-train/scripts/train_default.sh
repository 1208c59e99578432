#!/usr/bin/env bash
# The default model's training run (issue 20): the `nviews` preset on the real captures
# of ../shared/data/train (all but `lego`, a render whose transparent background the
# reader drops), plus procedural scenes; NeRF-format scenes get automatic depth bounds.
# Validated on scenes never trained on. Starts the run, or continues it from its committed checkpoint
# (`--resume`) when deepstereo-train/runs/nviews-real/checkpoint.safetensors exists.
# Run from the repository root: bash deepstereo-train/scripts/train_default.sh [STEPS] [LR_SCHEDULE]
# (OUT and VALIDATE_EVERY, default 200, from the environment: train_scratch.sh's run.)
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-deepstereo-train/runs/nviews-real}"
STEPS="${1:-8600}"
# Constant Adam 1e-3 to step 6000 (validation flat from ~1400), then a cosine decay to
# 5e-5 at step 8600 (added on resume at step 6030 as cosine:6000-10000, shortened at
# step 6501 to fit the session).
SCHEDULE="${2:-cosine:6000-8600}"
# shellcheck source=deepstereo-train/scripts/default_data.sh
source deepstereo-train/scripts/default_data.sh
cargo build --release -p deepstereo-train
# The run's own config (the nviews preset before it gained the view falloff).
exec nice -n 19 target/release/deepstereo train --config "$OUT/config.json" "${SAMPLING[@]}" \
  --steps "$STEPS" --batch 8 --optimizer adam --lr 1e-3 --seed 1 \
  --lr-schedule "$SCHEDULE" --lr-final 0.05 \
  --checkpoint-every 100 --validate-every "${VALIDATE_EVERY:-200}" --log-every 20 --no-progress \
  --out "$OUT" "${RESUME[@]}"
