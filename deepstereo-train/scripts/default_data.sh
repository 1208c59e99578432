# Sourced by train.sh (the default model's training recipes): the training scenes of
# ../shared/data/train (all but `lego`, a render whose transparent background the reader
# drops) and the scenes validated on, never trained on. Sets DATA, TRAIN and VAL, SAMPLING
# (the data and sampling options every run of the default model passes to `train`;
# VIEW_RANGE, default 2-10, sets the source views per batch, SYNTH_SIZE, default 240x180,
# the procedural scenes' image size; NO_AUGMENT=1 leaves out --augment) and, for run directory OUT, RESUME (`--resume` when
# OUT holds a checkpoint); run from the repository root. CORPUS=all adds the captures
# that came after the shipped model's runs (coke, desk, gum, plush: 17 scenes);
# CORPUS=forward adds to those the forward-facing captures (flower, fortress, canclip,
# ollie: 21 scenes) and validates on the forward-facing `val/room` too.
DATA=../shared/data
TRAIN=()
for s in bird blowtorch can cityscape cup duckqueen figurine fruit maryrose milk mouse plant statue; do
  TRAIN+=("$DATA/train/$s")
done
if [ "${CORPUS:-}" = all ] || [ "${CORPUS:-}" = forward ]; then
  for s in coke desk gum plush; do TRAIN+=("$DATA/train/$s"); done
fi
VAL=("$DATA/val/juicebox" "$DATA/val/moldgoldcape" "$DATA/val/stitch" "$DATA/templeRing" "$DATA/ethiopianHead" "$DATA/fox")
if [ "${CORPUS:-}" = forward ]; then
  for s in flower fortress canclip ollie; do TRAIN+=("$DATA/train/$s"); done
  VAL+=("$DATA/val/room")
fi
AUGMENT=(--augment)
if [ -n "${NO_AUGMENT:-}" ]; then AUGMENT=(); fi
SAMPLING=(--views "${VIEW_RANGE:-2-10}" --data "${TRAIN[@]}" --synthetic 200 --synth-size "${SYNTH_SIZE:-240x180}" --synth-views 12
  --synthetic-percent 40 "${AUGMENT[@]}" --val-data "${VAL[@]}" --val-scenes 8 --val-batches 8)
RESUME=()
if [ -f "$OUT/checkpoint.safetensors" ]; then RESUME=(--resume); fi
