#!/usr/bin/env bash
# Error against tuning time: `deepstereo tune` on each evaluation scene (every 8th view
# held out and never read; the scene flags of eval_default.sh), held-out PSNR / SSIM of
# the snapshots at 0, 1, 2, 5, 10 and 20 minutes within the budget and at its end (0 = the
# untuned model), one scene at a time.
# Writes OUT/NAME/{curve.csv,curve.json,curve.png,tune.log} and prints a markdown table.
# Usage: bash deepstereo-train/scripts/tune_curves.sh [OUT] [MINUTES] [MODEL]
#        ONLY="moldgoldcape fox" tunes only those scenes (the table shows every scene in OUT);
#        SEED=S tunes with --seed S (default 1).
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${1:-/tmp/deepstereo-tune}"
MINUTES="${2:-10}"
MODEL="${3:-embedded}"
BIN=target/release/deepstereo
mkdir -p "$OUT"
CURVE=$(python3 -c "import sys; m = float(sys.argv[1]); t = [x for x in (0, 1, 2, 5, 10, 20) if x < m] + [m]; print(','.join(f'{x:g}' for x in t))" "$MINUTES")
# shellcheck source=eval_scenes.sh
source deepstereo-train/scripts/eval_scenes.sh
for entry in "${EVAL_SCENES[@]}"; do
  dir="${entry%%|*}"; flags="${entry#*|}"; name="$(basename "$dir")"
  if [ ! -d "$dir" ]; then echo "skipped: $dir not found"; continue; fi
  if [ -n "${ONLY:-}" ] && [[ " $ONLY " != *" $name "* ]]; then continue; fi
  if [ -f "$OUT/$name/curve.json" ]; then echo "done before: $name"; continue; fi
  mkdir -p "$OUT/$name"
  # shellcheck disable=SC2086
  "$BIN" tune --scene "$dir" $flags --llffhold 8 --minutes "$MINUTES" --model "$MODEL" \
    --curve "$OUT/$name" --curve-minutes "$CURVE" --seed "${SEED:-1}" \
    --out "$OUT/$name/tuned.safetensors" 2> "$OUT/$name/tune.log"
  echo "done: $name"
done
python3 - "$OUT" <<'PY'
import json, re, sys, pathlib
out = pathlib.Path(sys.argv[1])
rows = []
for f in sorted(out.glob("*/curve.json")):
    pts = json.loads(f.read_text())["points"]
    log = (f.parent / "tune.log").read_text() if (f.parent / "tune.log").exists() else ""
    net = re.search(r"^network: (\d+) steps in (\d+) s", log, re.M)
    prior = re.search(r"^scene prior: (\d+) views.*?(?:sharpness ([\d.]+))?$", log, re.M)
    planes = re.search(r"^render planes: (\d+)", log, re.M)
    what = ", ".join([f"network {net[2]} s" if net else "no network",
                      (f"prior {prior[1]} views" + (f" (sharpness {float(prior[2]):.2f})" if prior[2] else "")) if prior else "no prior",
                      f"{planes[1]} planes" if planes else "planes as given"])
    rows.append((f.parent.name, pts, what))
if rows:
    mins = [p["minutes"] for p in rows[0][1]]
    print("| scene | " + " | ".join(f"{m:g} min PSNR / SSIM" for m in mins) + " | gain | tune | s/view untuned / tuned |")
    print("|---|" + "---|" * (len(mins) + 3))
    for name, pts, what in rows:
        cells = [f"{p['psnr']:.2f} / {p['ssim']:.3f}" for p in pts]
        gain = pts[-1]["psnr"] - pts[0]["psnr"]
        print(f"| {name} | " + " | ".join(cells) + f" | {gain:+.2f} | {what} | {pts[0]['seconds_per_view']:.2f} / {pts[-1]['seconds_per_view']:.2f} |")
    n = len(rows)
    print(f"| mean | " + " | ".join(f"{sum(r[1][i]['psnr'] for r in rows)/n:.2f}" for i in range(len(mins))) + f" | {sum(r[1][-1]['psnr']-r[1][0]['psnr'] for r in rows)/n:+.2f} | | |")
PY
