#!/usr/bin/env bash
# Models or render settings side by side on the evaluation scenes (every 8th view held
# out, the scene flags of eval_default.sh): per scene, each configuration's `eval`, one
# after the other, ROUNDS times (alternated, so a slower spell of the machine falls on
# all of them). Writes OUT/NAME.LABEL.ROUND.json (`eval --json`) and prints a markdown
# table: held-out PSNR / SSIM and the seconds per view of each configuration, with its
# mean time and the network's work (planes x pixels it ran, summed over the held-out
# views) as ratios of the first configuration's (python3, stdlib only).
# Usage: bash deepstereo-train/scripts/side_by_side.sh OUT ROUNDS 'LABEL|OPTIONS' ...
#        OPTIONS are `eval` options; {name} in them is the scene's base name, e.g.
#        'tuned|--model TUNE_OUT/{name}/tuned.safetensors' for tune_curves.sh's models.
#        ONLY="juicebox fox" runs only those scenes.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="$1"; ROUNDS="$2"; shift 2
CONFIGS=("$@")
[ "${#CONFIGS[@]}" -gt 0 ] || { echo "give at least one 'LABEL|OPTIONS'" >&2; exit 2; }
BIN=target/release/deepstereo
mkdir -p "$OUT"
# shellcheck source=eval_scenes.sh
source deepstereo-train/scripts/eval_scenes.sh
for entry in "${EVAL_SCENES[@]}"; do
  dir="${entry%%|*}"; flags="${entry#*|}"; name="$(basename "$dir")"
  if [ ! -d "$dir" ]; then echo "skipped: $dir not found"; continue; fi
  if [ -n "${ONLY:-}" ] && [[ " $ONLY " != *" $name "* ]]; then continue; fi
  for round in $(seq 1 "$ROUNDS"); do
    for c in "${CONFIGS[@]}"; do
      label="${c%%|*}"; opts="${c#*|}"; opts="${opts//\{name\}/$name}"
      json="$OUT/$name.$label.$round.json"
      [ -f "$json" ] && continue
      # shellcheck disable=SC2086
      "$BIN" eval --scene "$dir" $flags --llffhold 8 $opts --json "$json.tmp" 2> "$OUT/$name.$label.$round.log"
      mv "$json.tmp" "$json"
    done
  done
  echo "done: $name"
done
labels=()
for c in "${CONFIGS[@]}"; do labels+=("${c%%|*}"); done
python3 - "$OUT" "${labels[@]}" <<'PY'
import json, sys, pathlib
out, labels = pathlib.Path(sys.argv[1]), sys.argv[2:]
names = sorted({p.name.split(".")[0] for p in out.glob("*.json")})
print("| scene | " + " | ".join(f"{l}: PSNR / SSIM, s/view (time, work ratio)" for l in labels) + " |")
print("|---|" + "---|" * len(labels))
sums = {l: [] for l in labels}
for n in names:
    row, base, wbase = [n], None, None
    for l in labels:
        runs = [json.loads(p.read_text()) for p in sorted(out.glob(f"{n}.{l}.*.json"))]
        if not runs:
            row.append("-")
            continue
        m = runs[0]["mean"]
        secs = sum(r["mean"]["seconds"] for r in runs) / len(runs)
        work = sum((v.get("prune") or {}).get("planes_run", 0) for v in runs[0]["per_view"])
        base = secs if base is None else base
        wbase = work if wbase is None else wbase
        each = ", ".join(f"{r['mean']['seconds']:.2f}" for r in runs)
        wr = f"{work / wbase:.2f}x" if wbase else "-"
        row.append(f"{m['psnr']:.2f} / {m['ssim']:.3f}, {each} ({secs / base:.2f}x, {wr})")
        sums[l].append(m["psnr"])
    print("| " + " | ".join(row) + " |")
means = [f"{sum(v) / len(v):.2f}" if v else "-" for v in sums.values()]
print("| mean PSNR | " + " | ".join(means) + " |")
PY
