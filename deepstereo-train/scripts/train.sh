#!/usr/bin/env bash
# The training runs of the default model, as named recipes of one `deepstereo train`
# command (the scenes and sampling: default_data.sh).
#
# Usage: bash deepstereo-train/scripts/train.sh RECIPE [OUT]
#        bash deepstereo-train/scripts/train.sh --list
# Runs from any directory (it changes to the repository root). OUT is the run directory (default:
# the recipe's, under deepstereo-train/runs/); a run continues from OUT's checkpoint
# (`--resume`) when there is one. The environment may change a recipe's values: STEPS,
# LR_SCHEDULE, INIT, LR, VALIDATE_EVERY, VIEW_RANGE (source views per batch, default
# 2-10), SYNTH_SIZE (procedural scenes' size, default 240x180), LOSS, VIEW_STRIDE,
# SKIP_FLAT, SCENE_WEIGHTS (`train --loss/--view-stride/--skip-flat/--scene-weights`).
# DRY_RUN=1 prints the command instead of building and running it, and writes nothing.
#
# `disagree-scratch` made the shipped model (runs/nviews-disagree-scratch, from scratch;
# ship_default.sh turns it into deepstereo-train/assets/nviews-disagree-scratch.safetensors). The
# defaults before it: `weigh-scratch` (runs/nviews-weigh-scratch), and before that
# `default` (runs/nviews-real) then `prox` (runs/nviews-prox). The others are
# experiments; the ones of commit fda1758 and before started from (or, `scratch`, were
# compared with) nviews-prox's weights, and their runs and results are at that commit.
# The experiments that changed the architecture
# with a Python tool first (`wide`: widen.py, `encoder3`: spatial_encoder.py, `levels`:
# add_levels.py; runs nviews-wide, nviews-enc3, nviews-l4) are only at that commit
# (deepstereo-train/scripts/train_{wide,encoder3,levels}.sh there).
set -euo pipefail
cd "$(dirname "$0")/../.."
RUNS=deepstereo-train/runs
# runs/ keeps the shipped model's run and the run in progress; every other run (its
# config, log, checkpoint and weights) is in git at this commit, and a recipe that starts
# from one of its files takes it from there (docs/experiments.md lists them).
RUNS_COMMIT=781c573
# Restores the file PATH (under runs/) from RUNS_COMMIT when it is not in the tree.
restore() {
  local path="$1"
  if [ -z "$path" ] || [ -e "$path" ] || [[ "$path" != "$RUNS"/* ]]; then return 0; fi
  mkdir -p "$(dirname "$path")"
  if git show "$RUNS_COMMIT:$path" > "$path.tmp" 2>/dev/null; then
    mv "$path.tmp" "$path"
    echo "restored $path from commit $RUNS_COMMIT"
  else
    rm -f "$path.tmp"
  fi
}
PROX_CONFIG=$RUNS/nviews-prox/config.json
SHIPPED=$RUNS/nviews-prox/model.safetensors
# The default from commit c40fb32 to c4032f1, where the later fine-tunes start.
WEIGH=$RUNS/nviews-weigh-scratch/model.safetensors

# name|description, in the order --list prints them.
RECIPES=(
  "default|runs/nviews-real: the nviews architecture (the run's config.json) from scratch, Adam 1e-3, cosine:6000-8600 to 5e-5, seed 1"
  "prox|runs/nviews-prox: its config's 1:2 proximity falloff, fine-tuned from nviews-real at step 8600, Adam 2e-4, cosine:200-2000 to a tenth, seed 2 (the default until commit 0afcee9)"
  "prox2|runs/nviews-prox2: prox's weights fine-tuned 3000 more steps, cosine:500-3000"
  "falloff|runs/nviews-falloff: the nviews preset's 4:8 falloff, fine-tuned from nviews-real at step 8600, cosine:200-2200"
  "scratch|runs/nviews-scratch: prox's config trained from scratch as default, cosine:3000-5500, validation every 250"
  "v4|runs/nviews-v4: nviews-prox's weights fine-tuned with exactly 4 source views per batch, cosine:100-1500"
  "hires|runs/nviews-hires: nviews-prox's weights fine-tuned with procedural scenes at 360x270, cosine:100-1500"
  "l2|runs/nviews-l2: nviews-prox's weights fine-tuned with --loss l2, cosine:100-1200"
  "stride|runs/nviews-stride: nviews-prox's weights fine-tuned with --view-stride 1-3, cosine:100-1500"
  "flat|runs/nviews-flat: nviews-prox's weights fine-tuned with --skip-flat 0.02, cosine:100-1500"
  "weighted|runs/nviews-weighted: nviews-prox's weights fine-tuned with --scene-weights (360-degree captures x3), cosine:100-1500"
  "cue-scratch|runs/nviews-cue-scratch: the nviews-cue architecture (cue's config) from scratch on the whole corpus (17 scenes), 2-12 views, as default: Adam 1e-3, cosine:6000-8600 to 5e-5, seed 1"
  "corpus|runs/nviews-corpus: prox's architecture (its config: no cue) from scratch on the whole corpus (17 scenes), 2-12 views, as cue-scratch: Adam 1e-3, cosine:6000-8600 to 5e-5, seed 1"
  "weigh|runs/nviews-weigh: corpus's weights at step 8600 with the views weighed by their cue (python/add_cue.py --weigh: the weights start at 1, so step 0 renders as corpus), fine-tuned on the whole corpus with 2-12 views, Adam 2e-4, cosine:300-2500 to a tenth"
  "weigh-scratch|runs/nviews-weigh-scratch: weigh's architecture (its config) from scratch on the whole corpus, 2-12 views, as corpus: Adam 1e-3, cosine:6000-8600 to 5e-5, seed 1"
  "mpi|runs/nviews-mpi: weigh-scratch's weights and config fine-tuned for MPIs with --mpi-loss 1 (224x64 tiles, the target one of the reference's 3 nearest views, 4 source views, no augmentation), batch 4, Adam 5e-4, cosine:100-300 to a tenth"
  "mpi2|runs/nviews-mpi2: as mpi, with the pairs drawn at half resolution (--mpi-scale 2, 96x64 tiles: 192x128 pixels of the full images), 200 steps, cosine:50-200"
  "agree|runs/nviews-agree: weigh-scratch's weights with the colour-agreement gate of the views beyond the nearest four (its config.json: weigh-scratch's with pool.agree near 4, sigma 0.1), fine-tuned on the whole corpus with 2-12 views, Adam 2e-4, cosine:300-3000 to a tenth"
  "disagree|runs/nviews-disagree: weigh-scratch's weights with the views' colour disagreement as a sixth cue channel of their weights (python/add_cue.py --disagree 4: a zero column, so step 0 renders as weigh-scratch), fine-tuned on the whole corpus with 4-12 views, Adam 3e-4, cosine:100-1500 to a tenth"
  "disagree-prior|runs/nviews-disagree-prior: as disagree, with the weights starting as a colour gate (add_cue.py --disagree 4 --prior 1: one more hidden unit relu(q), output weight -1), 8-12 views, Adam 3e-4, cosine:0-600 to a tenth"
  "disagree-scratch|runs/nviews-disagree-scratch: the nviews-disagree preset (weigh-scratch's architecture with the disagreement channel) from scratch on the whole corpus, 2-12 views, as weigh-scratch: Adam 1e-3, cosine:6000-8600 to 5e-5, seed 1"
  "forward-scratch|runs/nviews-forward: disagree-scratch's preset and schedule (nviews-disagree, Adam 1e-3, cosine:6000-8600 to 5e-5, seed 1, 2-12 views) from scratch on the corpus plus the forward-facing captures (CORPUS=forward: 21 scenes, the five forward-facing ones drawn x3), validated on val/room too: what the data alone gives"
  "features-scratch|runs/nviews-features: the nviews-features preset (a CNN run once on each source image, its maps warped into the sweep beside the RGBA) from scratch on forward-scratch's data and schedule: the new family against the data alone"
  "cue|runs/nviews-cue: nviews-prox's weights given the per-view cue (python/add_cue.py: zero columns, so step 0 renders as nviews-prox), fine-tuned on the whole corpus (17 scenes) with 2-12 views, Adam 3e-4 to step 1600, then a cosine to a tenth at step 4500"
)

list() {
  echo "usage: bash deepstereo-train/scripts/train.sh RECIPE [OUT]   (DRY_RUN=1: print the command)"
  echo "recipes:"
  for r in "${RECIPES[@]}"; do printf '  %-9s %s\n' "${r%%|*}" "${r#*|}"; done
  echo "  (wide, encoder3, levels: architecture changes made with Python tools, at commit fda1758)"
}

RECIPE="${1:-}"
case "$RECIPE" in
  "" | --list | -l | --help | -h) list; exit 0 ;;
esac
if [ $# -gt 2 ]; then
  echo "error: too many arguments (STEPS and LR_SCHEDULE come from the environment)" >&2
  list >&2
  exit 2
fi

# A fine-tune of nviews-prox's weights (SHIPPED: the default until commit 0afcee9): the
# run's own copy of prox's config.
experiment() {
  : "${INIT:=$SHIPPED}" "${STEPS:=1500}" "${LR_SCHEDULE:=cosine:100-1500}"
  COPY_CONFIG=$PROX_CONFIG
}

# From scratch on a corpus (CORPUS, default the first argument, else all): default's
# schedule (cosine:6000-8600) with 2-12 views.
corpus_scratch() {
  : "${STEPS:=8600}" "${LR_SCHEDULE:=cosine:6000-8600}" "${VIEW_RANGE:=2-12}" "${CORPUS:=${1:-all}}"
}

# Fine-tunes (`--init`): Adam 2e-4, seed 2, a cosine down to a tenth, validation every
# 250 steps (the former finetune.sh); from scratch: Adam 1e-3, seed 1, a cosine down to
# 5e-5 (a twentieth), validation every 200 steps.
COPY_CONFIG=
CONFIG=
EXTRA=()
case "$RECIPE" in
  default)
    OUT="${2:-$RUNS/nviews-real}"
    : "${STEPS:=8600}" "${LR_SCHEDULE:=cosine:6000-8600}"
    # The run's own config (the nviews preset before it gained the view falloff).
    # Constant Adam 1e-3 to step 6000 (validation flat from ~1400), then a cosine decay to
    # 5e-5 at step 8600 (added on resume at step 6030 as cosine:6000-10000, shortened at
    # step 6501). The run then continued at 5e-5 to step 9577, no better.
    ;;
  prox)
    OUT="${2:-$RUNS/nviews-prox}"
    # nviews-real's weights at step 8600: the path its checkpoint records as --init.
    : "${INIT:=$RUNS/nviews-falloff/init.safetensors}" "${STEPS:=2000}" "${LR_SCHEDULE:=cosine:200-2000}"
    ;;
  prox2)
    OUT="${2:-$RUNS/nviews-prox2}"
    : "${INIT:=$SHIPPED}" "${STEPS:=3000}" "${LR_SCHEDULE:=cosine:500-3000}"
    COPY_CONFIG=$PROX_CONFIG
    ;;
  falloff)
    OUT="${2:-$RUNS/nviews-falloff}"
    CONFIG=nviews
    # Started as cosine:200-3000, shortened at step 1582.
    : "${INIT:=$RUNS/nviews-falloff/init.safetensors}" "${STEPS:=2200}" "${LR_SCHEDULE:=cosine:200-2200}"
    ;;
  scratch)
    OUT="${2:-$RUNS/nviews-scratch}"
    : "${STEPS:=5500}" "${LR_SCHEDULE:=cosine:3000-5500}" "${VALIDATE_EVERY:=250}"
    COPY_CONFIG=$PROX_CONFIG
    ;;
  v4) OUT="${2:-$RUNS/nviews-v4}"; experiment; : "${VIEW_RANGE:=4}" ;;
  hires) OUT="${2:-$RUNS/nviews-hires}"; experiment; : "${SYNTH_SIZE:=360x270}" ;;
  l2)
    OUT="${2:-$RUNS/nviews-l2}"
    : "${LOSS:=l2}" "${STEPS:=1200}" "${LR_SCHEDULE:=cosine:100-1200}"; experiment
    ;;
  stride) OUT="${2:-$RUNS/nviews-stride}"; experiment; : "${VIEW_STRIDE:=1-3}" ;;
  flat) OUT="${2:-$RUNS/nviews-flat}"; experiment; : "${SKIP_FLAT:=0.02}" ;;
  weighted)
    OUT="${2:-$RUNS/nviews-weighted}"; experiment
    : "${SCENE_WEIGHTS:=blowtorch=3,maryrose=3,milk=3,plant=3}"
    ;;
  cue-scratch)
    OUT="${2:-$RUNS/nviews-cue-scratch}"
    corpus_scratch
    COPY_CONFIG=$RUNS/nviews-cue/config.json
    ;;
  corpus)
    OUT="${2:-$RUNS/nviews-corpus}"
    corpus_scratch
    COPY_CONFIG=$PROX_CONFIG
    ;;
  weigh)
    OUT="${2:-$RUNS/nviews-weigh}"
    # init.safetensors and config.json: python/add_cue.py --weigh on runs/nviews-corpus/model.safetensors.
    : "${INIT:=$RUNS/nviews-weigh/init.safetensors}" "${STEPS:=2500}" "${LR_SCHEDULE:=cosine:300-2500}"
    : "${VIEW_RANGE:=2-12}" "${CORPUS:=all}"
    ;;
  weigh-scratch)
    OUT="${2:-$RUNS/nviews-weigh-scratch}"
    corpus_scratch
    COPY_CONFIG=$RUNS/nviews-weigh/config.json
    ;;
  agree)
    OUT="${2:-$RUNS/nviews-agree}"
    # config.json: runs/nviews-weigh-scratch/config.json with "agree": {"near": 4, "sigma": 0.1} in its pool.
    : "${INIT:=$WEIGH}" "${STEPS:=3000}" "${LR_SCHEDULE:=cosine:300-3000}"
    : "${VIEW_RANGE:=2-12}" "${CORPUS:=all}"
    ;;
  disagree)
    OUT="${2:-$RUNS/nviews-disagree}"
    # init.safetensors and config.json: python/add_cue.py --disagree 4 on runs/nviews-weigh-scratch's weights.
    : "${INIT:=$RUNS/nviews-disagree/init.safetensors}" "${STEPS:=1500}" "${LR_SCHEDULE:=cosine:100-1500}"
    : "${LR:=3e-4}" "${VIEW_RANGE:=4-12}" "${CORPUS:=all}"
    ;;
  disagree-prior)
    OUT="${2:-$RUNS/nviews-disagree-prior}"
    # init.safetensors and config.json: python/add_cue.py --disagree 4 --prior 1 on runs/nviews-weigh-scratch's weights.
    : "${INIT:=$RUNS/nviews-disagree-prior/init.safetensors}" "${STEPS:=600}" "${LR_SCHEDULE:=cosine:0-600}"
    : "${LR:=3e-4}" "${VIEW_RANGE:=8-12}" "${CORPUS:=all}" "${VALIDATE_EVERY:=200}"
    ;;
  disagree-scratch)
    OUT="${2:-$RUNS/nviews-disagree-scratch}"
    CONFIG=nviews-disagree
    corpus_scratch
    ;;
  forward-scratch)
    OUT="${2:-$RUNS/nviews-forward}"
    CONFIG=nviews-disagree
    corpus_scratch forward
    : "${SCENE_WEIGHTS:=desk=3,flower=3,fortress=3,canclip=3,ollie=3}"
    ;;
  features-scratch)
    OUT="${2:-$RUNS/nviews-features}"
    CONFIG=nviews-features
    : "${STEPS:=8600}" "${LR_SCHEDULE:=cosine:6000-8600}" "${VIEW_RANGE:=2-12}" "${CORPUS:=forward}"
    : "${SCENE_WEIGHTS:=desk=3,flower=3,fortress=3,canclip=3,ollie=3}"
    ;;
  cue)
    OUT="${2:-$RUNS/nviews-cue}"
    # init.safetensors and config.json: python/add_cue.py on nviews-prox's weights.
    : "${INIT:=$RUNS/nviews-cue/init.safetensors}" "${STEPS:=4500}" "${LR_SCHEDULE:=cosine:1600-4500}"
    # Started as cosine:300-7000; shortened to 6000 at step 800; the validation PSNR fell
    # from 24.31 (step 500) to 24.08 (step 1500) at 3e-4, so from step 1600 the rate decays
    # at once: cosine:1600-4500.
    : "${LR:=3e-4}" "${VIEW_RANGE:=2-12}" "${CORPUS:=all}"
    ;;
  mpi | mpi2)
    OUT="${2:-$RUNS/nviews-$RECIPE}"
    if [ "$RECIPE" = mpi ]; then
      : "${STEPS:=300}" "${LR_SCHEDULE:=cosine:100-300}"
      PAIRS=(--mpi-tile 224x64 --mpi-neighbours 3)
    else
      : "${STEPS:=200}" "${LR_SCHEDULE:=cosine:50-200}"
      PAIRS=(--mpi-tile 96x64 --mpi-neighbours 3 --mpi-scale 2)
    fi
    : "${INIT:=$WEIGH}"
    : "${VIEW_RANGE:=4}" "${CORPUS:=all}" "${BATCH:=4}" "${VALIDATE_EVERY:=100}" "${LR:=5e-4}"
    COPY_CONFIG=$RUNS/nviews-weigh-scratch/config.json
    NO_AUGMENT=1
    EXTRA=(--mpi-loss 1 "${PAIRS[@]}")
    ;;
  wide | encoder3 | levels)
    echo "error: recipe '$RECIPE' changed the architecture with a Python tool first; it is at commit fda1758 (deepstereo-train/scripts/train_$RECIPE.sh)" >&2
    exit 2
    ;;
  *)
    echo "error: unknown recipe '$RECIPE'" >&2
    list >&2
    exit 2
    ;;
esac
CONFIG="${CONFIG:-$OUT/config.json}"
if [ -n "${INIT:-}" ]; then
  : "${LR:=2e-4}" "${SEED:=2}" "${LR_FINAL:=0.1}" "${VALIDATE_EVERY:=250}"
else
  : "${LR:=1e-3}" "${SEED:=1}" "${LR_FINAL:=0.05}" "${VALIDATE_EVERY:=200}"
fi

# shellcheck source=deepstereo-train/scripts/default_data.sh
source deepstereo-train/scripts/default_data.sh
CMD=(nice -n 19 target/release/deepstereo train --config "$CONFIG" ${INIT:+--init "$INIT"} "${SAMPLING[@]}"
  --steps "$STEPS" --batch "${BATCH:-8}" --optimizer adam --lr "$LR" --seed "$SEED"
  --lr-schedule "$LR_SCHEDULE" --lr-final "$LR_FINAL"
  --checkpoint-every 100 --validate-every "$VALIDATE_EVERY" --log-every 20 --no-progress
  ${LOSS:+--loss "$LOSS"} ${VIEW_STRIDE:+--view-stride "$VIEW_STRIDE"}
  ${SKIP_FLAT:+--skip-flat "$SKIP_FLAT"} ${SCENE_WEIGHTS:+--scene-weights "$SCENE_WEIGHTS"}
  "${EXTRA[@]}" --out "$OUT" "${RESUME[@]}")
if [ -n "${DRY_RUN:-}" ]; then
  if [ -n "$COPY_CONFIG" ] && [ ! -f "$CONFIG" ]; then echo "# would copy $COPY_CONFIG to $CONFIG"; fi
  printf '%q ' "${CMD[@]}"
  echo
  exit 0
fi
restore "${INIT:-}"
restore "$CONFIG"
restore "$COPY_CONFIG"
if [ -n "$COPY_CONFIG" ] && [ ! -f "$CONFIG" ]; then
  mkdir -p "$OUT"
  cp "$COPY_CONFIG" "$CONFIG"
fi
cargo build --release -p deepstereo-train
exec "${CMD[@]}"
