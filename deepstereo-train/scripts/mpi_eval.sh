#!/usr/bin/env bash
# Held-out views through MPIs: on each evaluation scene (every 8th view held out, the
# scene flags of eval_default.sh), each held-out view rendered by the network and through
# MPIs baked at its nearest views that are not held out (`deepstereo mpi --eval`), in
# three settings: one MPI with its reference photograph among the sources (as
# `mpi --target`), one without it (`--exclude-own-photo`), and three without, blended.
# Writes OUT/NAME.SETTING/eval.json and prints a markdown table (python3, stdlib only).
# Usage: bash deepstereo-train/scripts/mpi_eval.sh [OUT] [MODEL]
#        SPEED_ONLY=1 runs only the camera-path timing at the end.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${1:-/tmp/deepstereo-mpi-eval}"
MODEL="${2:-embedded}"
BIN=target/release/deepstereo
mkdir -p "$OUT"
# shellcheck source=eval_scenes.sh
source deepstereo-train/scripts/eval_scenes.sh
SETTINGS=(
  "own1|--eval-mpis 1"
  "other1|--eval-mpis 1 --exclude-own-photo"
  "other3|--eval-mpis 3 --exclude-own-photo"
)
[ -n "${SPEED_ONLY:-}" ] && EVAL_SCENES=()
for entry in "${EVAL_SCENES[@]}"; do
  dir="${entry%%|*}"; flags="${entry#*|}"; name="$(basename "$dir")"
  if [ ! -d "$dir" ]; then echo "skipped: $dir not found"; continue; fi
  for s in "${SETTINGS[@]}"; do
    tag="${s%%|*}"; opts="${s#*|}"
    [ -f "$OUT/$name.$tag/eval.json" ] && continue
    # shellcheck disable=SC2086
    "$BIN" mpi --scene "$dir" $flags --llffhold 8 --model "$MODEL" --eval $opts \
      --out "$OUT/$name.$tag" 2> "$OUT/$name.$tag.log"
  done
  echo "done: $name"
done
python3 - "$OUT" <<'PY'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1])
names = sorted({p.name.split(".")[0] for p in out.glob("*.own1")})
tags = [("own1", "1 MPI, own photo"), ("other1", "1 MPI, other views"), ("other3", "3 MPIs, other views")]
print("| scene | network PSNR / SSIM, s/view | " + " | ".join(f"{t}: PSNR / SSIM (vs network)" for _, t in tags) + " | MPI frame s (1 / 3 MPIs) | bake s per MPI |")
print("|---|---|" + "---|" * len(tags) + "---|---|")
for n in names:
    j = {t: json.loads((out / f"{n}.{t}/eval.json").read_text()) for t, _ in tags if (out / f"{n}.{t}/eval.json").exists()}
    if "own1" not in j: continue
    m = j["own1"]["mean"]
    row = [n, f"{m['network_psnr']:.2f} / {m['network_ssim']:.3f}, {m['network_seconds']:.2f}"]
    for t, _ in tags:
        if t in j:
            mm = j[t]["mean"]
            row.append(f"{mm['mpi_psnr']:.2f} / {mm['mpi_ssim']:.3f} ({mm['mpi_psnr'] - mm['network_psnr']:+.2f})")
        else:
            row.append("-")
    f1 = j["other1"]["mean"]["mpi_render_seconds"] if "other1" in j else float("nan")
    f3 = j["other3"]["mean"]["mpi_render_seconds"] if "other3" in j else float("nan")
    row.append(f"{f1:.3f} / {f3:.3f}")
    row.append(f"{j['own1']['mean']['bake_seconds']:.2f}")
    print("| " + " | ".join(row) + " |")
PY
# Speed: a camera path through the network and through 3 MPIs, one after the other,
# twice; whole-command wall time per frame (loading the model or the MPIs included).
S="$DATA/val/juicebox"
FRAMES=12
if [ -d "$S" ]; then
  [ -d "$OUT/speed_mpis" ] || "$BIN" mpi --scene "$S" --targets 1,9,17 --model "$MODEL" --out "$OUT/speed_mpis" 2> /dev/null
  for round in 1 2; do
    for kind in network mpi; do
      rm -rf "$OUT/speed_$kind$round"
      extra=(--model "$MODEL"); [ "$kind" = mpi ] && extra=(--mpi "$OUT/speed_mpis")
      t0=$(date +%s.%N)
      "$BIN" render --scene "$S" "${extra[@]}" --path spiral --frames "$FRAMES" --out "$OUT/speed_$kind$round" 2> /dev/null
      t1=$(date +%s.%N)
      echo "$kind round $round: $(python3 -c "print(f'{($t1 - $t0) / $FRAMES:.3f}')") s per frame ($FRAMES frames of $(basename "$S"))"
    done
  done
fi
