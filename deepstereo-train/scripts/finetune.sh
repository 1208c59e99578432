#!/usr/bin/env bash
# The default model's fine-tuning runs (train_falloff.sh, train_prox.sh): `train --init`
# from a model's weights with the `nviews` architecture and config CONFIG (a preset or a
# JSON file), on the default run's scenes (default_data.sh), views 2-10 per batch,
# photometric augmentation and flips, Adam at LR (default 2e-4) and the schedule SCHEDULE
# down to a tenth of it, seed 2, the loss LOSS when set (default L1), the source stride
# VIEW_STRIDE when set (`train --view-stride`; default: the nearest views), the flat-tile
# threshold SKIP_FLAT when set (`train --skip-flat`; default: every tile), the scene
# weights SCENE_WEIGHTS when set (`train --scene-weights`; default: all alike). Continues from
# OUT's committed checkpoint when there is one.
# Run from the repository root: OUT=DIR INIT=MODEL CONFIG=CFG bash deepstereo-train/scripts/finetune.sh STEPS SCHEDULE
set -euo pipefail
cd "$(dirname "$0")/../.."
: "${OUT:?OUT (the run directory) is required}" "${INIT:?INIT (the starting weights) is required}"
: "${CONFIG:?CONFIG (a preset or a config JSON) is required}"
STEPS="${1:?STEPS is required}"
SCHEDULE="${2:?LR_SCHEDULE is required}"
# shellcheck source=deepstereo-train/scripts/default_data.sh
source deepstereo-train/scripts/default_data.sh
cargo build --release -p deepstereo-train
exec nice -n 19 target/release/deepstereo train --config "$CONFIG" --init "$INIT" "${SAMPLING[@]}" \
  --steps "$STEPS" --batch 8 --optimizer adam --lr "${LR:-2e-4}" --seed 2 \
  --lr-schedule "$SCHEDULE" --lr-final 0.1 \
  --checkpoint-every 100 --validate-every 250 --log-every 20 --no-progress \
  ${LOSS:+--loss "$LOSS"} ${VIEW_STRIDE:+--view-stride "$VIEW_STRIDE"} \
  ${SKIP_FLAT:+--skip-flat "$SKIP_FLAT"} ${SCENE_WEIGHTS:+--scene-weights "$SCENE_WEIGHTS"} --out "$OUT" "${RESUME[@]}"
