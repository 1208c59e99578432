# The real evaluation scenes (never trained on; the six object and outdoor captures of
# the README's table, then the forward-facing val/room) and the flags each is read with, as
# "DIR|FLAGS", and the procedural evaluation scenes: sourced by eval_default.sh,
# eval_views.sh, prune_eval.sh, bench_render.sh, tune_curves.sh and mpi_eval.sh after
# they cd to the repository root (../shared/data beside it).
DATA="${DATA:-../shared/data}"
EVAL_SCENES=(
  "$DATA/val/juicebox|"
  "$DATA/val/moldgoldcape|"
  "$DATA/val/stitch|"
  "$DATA/fox|--downscale 4"
  "$DATA/templeRing|--downscale 2"
  "$DATA/ethiopianHead|--downscale 4"
  "$DATA/val/room|"
)

# The first N (default 2) procedural evaluation scenes, of a seed no run trains on
# (training draws its procedural scenes from --seed 1 and validation from
# 1 ^ VALIDATION_SALT), 504x378, 12 views each, in DIR/procedural/scene_000K (made once).
procedural_scenes() {
  local dir="$1" n="${2:-2}"
  if [ ! -d "$dir/procedural/scene_$(printf %04d $((n - 1)))" ]; then
    target/release/deepstereo synth --out "$dir/procedural" --scenes "$n" --seed 987654 \
      --size 504x378 --views 12 > /dev/null
  fi
}

# ALL_SCENES: the real evaluation scenes and the first two procedural ones in DIR (made
# once), as "DIR|FLAGS".
all_eval_scenes() {
  procedural_scenes "$1" 2
  ALL_SCENES=("${EVAL_SCENES[@]}" "$1/procedural/scene_0000|" "$1/procedural/scene_0001|")
}

# Calls `$1 DIR FLAGS NAME` on each of the scenes all_eval_scenes lists for OUT (`$2`,
# made first), skipping those whose directory is missing (and saying so), and says
# "done: NAME" after each.
each_eval_scene() {
  local run="$1" entry dir
  mkdir -p "$2"
  all_eval_scenes "$2"
  for entry in "${ALL_SCENES[@]}"; do
    dir="${entry%%|*}"
    if [ ! -d "$dir" ]; then echo "skipped: $dir not found"; continue; fi
    "$run" "$dir" "${entry#*|}" "$(scene_name "$dir")"
    echo "done: $(scene_name "$dir")"
  done
}

# The name results are filed under: a scene directory's base name, procedural-000K for
# the procedural scenes.
scene_name() {
  local name
  name="$(basename "$1")"
  case "$1" in */procedural/scene_*) name="procedural-${name#scene_}" ;; esac
  echo "$name"
}
