# The real evaluation scenes (never trained on) and the flags each is read with, as
# "DIR|FLAGS": sourced by eval_default.sh, tune_curves.sh and mpi_eval.sh after they cd
# to the repository root (../shared/data beside it).
DATA="${DATA:-../shared/data}"
EVAL_SCENES=(
  "$DATA/val/juicebox|"
  "$DATA/val/moldgoldcape|"
  "$DATA/val/stitch|"
  "$DATA/fox|--downscale 4"
  "$DATA/templeRing|--downscale 2"
  "$DATA/ethiopianHead|--downscale 4"
)
