#!/usr/bin/env bash
# Issue 17/20 measurements: a model (default: the shipped default, the embedded asset) against
# `tiny` (the embedded model before nviews-real, deepstereo-train/assets/tiny.safetensors)
# and the classical plane sweep (same sources and planes) on scenes
# never trained on, with the field's protocol (every 8th view held out, sources among the
# other views only, PSNR / SSIM over the whole image), at --views 4 and 8 (and 2).
# Writes JSON per run into OUT and prints a markdown table (python3, stdlib only).
# Usage: bash deepstereo-train/scripts/eval_default.sh [MODEL] [OUT] [VIEWS...]
set -euo pipefail
cd "$(dirname "$0")/../.."
MODEL="${1:-deepstereo-train/assets/nviews-disagree-scratch.safetensors}"
OUT="${2:-/tmp/deepstereo-eval}"
shift $(( $# > 2 ? 2 : $# ))
if [ $# -gt 0 ]; then VIEWS=("$@"); else VIEWS=(4 8); fi
# shellcheck source=eval_scenes.sh
source deepstereo-train/scripts/eval_scenes.sh
BIN=target/release/deepstereo
TINY=deepstereo-train/assets/tiny.safetensors
# One scene: `tiny` at 4 views, then the model at each of VIEWS.
eval_scene() {
  local dir="$1" flags="$2" name="$3"
  # shellcheck disable=SC2086
  nice "$BIN" eval --scene "$dir" $flags --llffhold 8 --views 4 --model "$TINY" \
    --json "$OUT/$name.embedded.json" > /dev/null
  for v in "${VIEWS[@]}"; do
    # shellcheck disable=SC2086
    nice "$BIN" eval --scene "$dir" $flags --llffhold 8 --model "$MODEL" --views "$v" \
      --json "$OUT/$name.model.v$v.json" > /dev/null
  done
}
each_eval_scene eval_scene "$OUT"
python3 - "$OUT" "${VIEWS[@]}" <<'PY'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1]); views = sys.argv[2:]
print("| scene | `tiny` (4 views) PSNR / SSIM, s/view | " + " | ".join(f"new, {v} views: PSNR / SSIM, s/view | plane sweep, {v} views: PSNR / SSIM" for v in views) + " |")
print("|---|---|" + "---|---|" * len(views))
for e in sorted(out.glob("*.embedded.json")):
    name = e.name.split(".")[0]
    m = json.loads(e.read_text())["mean"]
    row = [name, f"{m['psnr']:.2f} / {m['ssim']:.3f}, {m['seconds']:.2f}"]
    for v in views:
        f = out / f"{name}.model.v{v}.json"
        if not f.exists():
            row += ["-", "-"]; continue
        n = json.loads(f.read_text())["mean"]; ps = n["baselines"]["plane_sweep"]
        row += [f"{n['psnr']:.2f} / {n['ssim']:.3f}, {n['seconds']:.2f}", f"{ps['psnr']:.2f} / {ps['ssim']:.3f}"]
    print("| " + " | ".join(row) + " |")
PY
