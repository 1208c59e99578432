# Sourced by the default model's training scripts (train_default.sh, train_falloff.sh):
# the training scenes of ../shared/data/train (all but `lego`, a render whose transparent
# background the reader drops) and the scenes validated on, never trained on. Sets DATA,
# TRAIN and VAL; run from the repository root.
DATA=../shared/data
TRAIN=()
for s in bird blowtorch can cityscape cup duckqueen figurine fruit maryrose milk mouse plant statue; do
  TRAIN+=("$DATA/train/$s")
done
VAL=("$DATA/val/juicebox" "$DATA/val/moldgoldcape" "$DATA/val/stitch" "$DATA/templeRing" "$DATA/ethiopianHead" "$DATA/fox")
