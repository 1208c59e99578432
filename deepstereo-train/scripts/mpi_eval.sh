#!/usr/bin/env bash
# Held-out views through MPIs: on each evaluation scene (every 8th view held out, the
# scene flags of eval_default.sh), each held-out view rendered by the network and through
# MPIs baked at its nearest views that are not held out (`deepstereo mpi --eval`), in
# three settings: one MPI with its reference photograph among the sources (as
# `mpi --target`), one without it (`--exclude-own-photo`), and three without, blended.
# Writes OUT/NAME.SETTING/eval.json and prints a markdown table (python3, stdlib only).
# Usage: bash deepstereo-train/scripts/mpi_eval.sh [OUT] [MODEL]
#        MODEL may name each scene's own model with {name}, the scene's base name, as
#        tune_curves.sh writes them: OUT_TUNE/{name}/tuned.safetensors.
#        SPEED_ONLY=1 runs only the camera-path timing at the end, NO_SPEED=1 skips it;
#        ONLY="other1 ..." runs only those settings; EXTRA="--views 8 --planes 64" adds
#        options to every `mpi`; PEER=PATH/TO/deepstereo also times the same MPIs' paths
#        with that binary (another version of the renderer) in every round, alternated.
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
    if [ -n "${ONLY:-}" ] && [[ " $ONLY " != *" $tag "* ]]; then continue; fi
    # shellcheck disable=SC2086
    "$BIN" mpi --scene "$dir" $flags --llffhold 8 --model "${MODEL//\{name\}/$name}" --eval $opts ${EXTRA:-} \
      --out "$OUT/$name.$tag" 2> "$OUT/$name.$tag.log"
  done
  echo "done: $name"
done
python3 - "$OUT" <<'PY'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1])
names = sorted({p.parent.name.split(".")[0] for p in out.glob("*.*/eval.json")})
tags = [("own1", "1 MPI, own photo"), ("other1", "1 MPI, other views"), ("other3", "3 MPIs, other views")]
print("| scene | network PSNR / SSIM, s/view | " + " | ".join(f"{t}: PSNR / SSIM (vs network)" for _, t in tags) + " | MPI frame s (1 / 3 MPIs) | bake s per MPI |")
print("|---|---|" + "---|" * len(tags) + "---|---|")
for n in names:
    j = {t: json.loads((out / f"{n}.{t}/eval.json").read_text()) for t, _ in tags if (out / f"{n}.{t}/eval.json").exists()}
    if not j: continue
    first = next(iter(j.values()))
    m = first["mean"]
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
    row.append(f"{m['bake_seconds'] / first['mpis_per_view']:.2f}")
    print("| " + " | ".join(row) + " |")
PY
# Speed: a spiral camera path on juicebox through the network and through one and three
# MPIs, twice, one command after the other. Seconds per frame are marginal: the wall-time
# difference of two path lengths over the frames added (network: 2 and 6 frames; MPIs: 12
# and 60), so loading the model or the MPIs and writing the video are not counted.
S="$DATA/val/juicebox"
SM="${MODEL//\{name\}/juicebox}"
if [ -d "$S" ] && [ -z "${NO_SPEED:-}" ]; then
  [ -d "$OUT/speed_mpis3" ] || "$BIN" mpi --scene "$S" --targets 1,9,17 --model "$SM" --out "$OUT/speed_mpis3" 2> /dev/null
  [ -d "$OUT/speed_mpis1" ] || "$BIN" mpi --scene "$S" --target 9 --model "$SM" --out "$OUT/speed_mpis1" 2> /dev/null
  # path_seconds FRAMES ARGS...: wall seconds of one `render --path spiral` (by $RUN).
  RUN="$BIN"
  path_seconds() {
    local frames="$1"; shift
    rm -rf "$OUT/speed_path"
    local t0 t1
    t0=$(date +%s.%N)
    "$RUN" render --scene "$S" "$@" --path spiral --frames "$frames" --out "$OUT/speed_path" 2> /dev/null
    t1=$(date +%s.%N)
    python3 -c "print($t1 - $t0)"
  }
  for round in 1 2; do
    n2=$(path_seconds 2 --model "$SM"); n6=$(path_seconds 6 --model "$SM")
    a12=$(path_seconds 12 --mpi "$OUT/speed_mpis1"); a60=$(path_seconds 60 --mpi "$OUT/speed_mpis1")
    b12=$(path_seconds 12 --mpi "$OUT/speed_mpis3"); b60=$(path_seconds 60 --mpi "$OUT/speed_mpis3")
    python3 - "$round" "$n2" "$n6" "$a12" "$a60" "$b12" "$b60" <<'PY'
import sys
r, n2, n6, a12, a60, b12, b60 = sys.argv[1], *map(float, sys.argv[2:])
n, m1, m3 = (n6 - n2) / 4, (a60 - a12) / 48, (b60 - b12) / 48
print(f"round {r}: network {n:.3f} s/frame; 1 MPI {m1:.4f} s/frame ({n / m1:.0f}x); "
      f"3 MPIs {m3:.4f} s/frame ({n / m3:.0f}x)")
PY
    if [ -n "${PEER:-}" ]; then
      RUN="$PEER"
      p12=$(path_seconds 12 --mpi "$OUT/speed_mpis1"); p60=$(path_seconds 60 --mpi "$OUT/speed_mpis1")
      q12=$(path_seconds 12 --mpi "$OUT/speed_mpis3"); q60=$(path_seconds 60 --mpi "$OUT/speed_mpis3")
      RUN="$BIN"
      python3 - "$round" "$a12" "$a60" "$b12" "$b60" "$p12" "$p60" "$q12" "$q60" <<'PY'
import sys
r, a12, a60, b12, b60, p12, p60, q12, q60 = sys.argv[1], *map(float, sys.argv[2:])
m1, m3, p1, p3 = (a60 - a12) / 48, (b60 - b12) / 48, (p60 - p12) / 48, (q60 - q12) / 48
print(f"round {r}: peer 1 MPI {p1:.4f} s/frame (this one {m1 / p1:.2f}x its time); "
      f"3 MPIs {p3:.4f} s/frame ({m3 / p3:.2f}x)")
PY
    fi
  done
fi
