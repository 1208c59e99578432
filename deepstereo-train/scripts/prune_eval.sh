#!/usr/bin/env bash
# Pruning against the plain renderer: `eval --llffhold 8` with `--prune off` and `--prune
# auto` (the defaults) at 32, 64 and 96 planes on the evaluation scenes (eval_scenes.sh)
# and two procedural scenes, the two modes run back to back per scene and plane count.
# Writes one JSON per run into OUT, then prints a markdown table (PSNR / SSIM, seconds per
# view, speed-up) and the checks of "pruning pays" (python3, stdlib only). Runs already
# in OUT are kept (rerun to continue).
# Usage: bash deepstereo-train/scripts/prune_eval.sh [MODEL] [OUT]
#        PLANES (default "32 64 96") the plane counts; EXTRA flags for the auto runs.
set -euo pipefail
cd "$(dirname "$0")/../.."
MODEL="${1:-embedded}"
OUT="${2:-/tmp/deepstereo-prune}"
# shellcheck disable=SC2206
PLANES=(${PLANES:-32 64 96})
# shellcheck source=eval_scenes.sh
source deepstereo-train/scripts/eval_scenes.sh
BIN=target/release/deepstereo
# One scene: each plane count with --prune off, then auto (runs in OUT kept).
eval_scene() {
  local dir="$1" flags="$2" name="$3"
  for p in "${PLANES[@]}"; do
    for mode in off auto; do
      json="$OUT/$name.p$p.$mode.json"
      [ -f "$json" ] && continue
      extra=""; [ "$mode" = auto ] && extra="${EXTRA:-}"
      # shellcheck disable=SC2086
      "$BIN" eval --scene "$dir" $flags --llffhold 8 --model "$MODEL" --planes "$p" \
        --prune "$mode" $extra --json "$json.tmp" > /dev/null && mv "$json.tmp" "$json"
    done
  done
  return 0 # a run that failed above (kept out of OUT) does not stop the others
}
each_eval_scene eval_scene "$OUT"
python3 - "$OUT" "${PLANES[@]}" <<'PY'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1]); planes = sys.argv[2:]
def load(n, p, m):
    f = out / f"{n}.p{p}.{m}.json"
    return json.loads(f.read_text())["mean"] if f.exists() else None
names = sorted({f.name.split(".")[0] for f in out.glob("*.p*.*.json")})
print("| scene | planes | off: PSNR / SSIM, s/view | auto: PSNR / SSIM, s/view | speed-up | PSNR auto - off |")
print("|---|---|---|---|---|---|")
fails = []
for n in names:
    for p in planes:
        a, b = load(n, p, "off"), load(n, p, "auto")
        if not (a and b):
            continue
        x, d = a["seconds"] / b["seconds"], b["psnr"] - a["psnr"]
        print(f"| {n} | {p} | {a['psnr']:.2f} / {a['ssim']:.3f}, {a['seconds']:.2f} | "
              f"{b['psnr']:.2f} / {b['ssim']:.3f}, {b['seconds']:.2f} | {x:.2f}x | {d:+.2f} |")
        if p in ("64", "96") and (x < 2.0 or d < -0.2):
            fails.append(f"{n} at {p} planes: {x:.2f}x, {d:+.2f} dB (needs >= 2x, >= -0.2 dB)")
        if p == "32" and x < 1.0:
            fails.append(f"{n} at 32 planes: {x:.2f}x (needs >= 1x)")
print()
print("all checks hold" if not fails else "fails:\n" + "\n".join(fails))
PY
