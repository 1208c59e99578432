#!/usr/bin/env bash
# Error against the number of source views: a model and a base model (default: the
# embedded default) at 2, 4, 8 and 10 views on the evaluation scenes (eval_scenes.sh) and
# two procedural scenes, with the field's protocol (`eval --llffhold 8`: every 8th view
# held out, sources among the others, PSNR / SSIM over the whole image). Writes one JSON
# per run into OUT and prints a markdown table and the checks of "more views help"
# (python3, stdlib only). Runs already in OUT are kept (rerun to continue).
# Usage: bash deepstereo-train/scripts/eval_views.sh MODEL [OUT] [BASE]
#        ONLY=base|model restricts the runs to one of the two models; MODEL_VIEWS and
#        BASE_VIEWS (default "2 4 8 10") the model's and the base's view counts; EXTRA flags for every run (e.g. "--planes
#        64"; give each EXTRA its own OUT).
set -euo pipefail
cd "$(dirname "$0")/../.."
MODEL="${1:?usage: eval_views.sh MODEL [OUT] [BASE]}"
OUT="${2:-/tmp/deepstereo-views}"
BASE="${3:-embedded}"
# shellcheck disable=SC2206
VIEWS=(${MODEL_VIEWS:-2 4 8 10})
# shellcheck source=eval_scenes.sh
source deepstereo-train/scripts/eval_scenes.sh
BIN=target/release/deepstereo
TAGS=()
case "${ONLY:-}" in
  base) TAGS=(base) ;;
  model) TAGS=(model) ;;
  *) TAGS=(model base) ;;
esac
# One scene: each of TAGS' models at each of its view counts (runs in OUT kept).
eval_scene() {
  local dir="$1" flags="$2" name="$3"
  for tag in "${TAGS[@]}"; do
    m="$MODEL"; [ "$tag" = base ] && m="$BASE"
    counts=("${VIEWS[@]}")
    # shellcheck disable=SC2206
    [ "$tag" = base ] && counts=(${BASE_VIEWS:-${VIEWS[*]}})
    for v in "${counts[@]}"; do
      json="$OUT/$name.$tag.v$v.json"
      [ -f "$json" ] && continue
      # shellcheck disable=SC2086
      "$BIN" eval --scene "$dir" $flags --llffhold 8 --model "$m" --views "$v" \
        ${EXTRA:-} --json "$json.tmp" > /dev/null && mv "$json.tmp" "$json"
    done
  done
  return 0 # a run that failed above (kept out of OUT) does not stop the others
}
each_eval_scene eval_scene "$OUT"
python3 - "$OUT" "${VIEWS[@]}" <<'PY'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1]); views = sys.argv[2:]
def load(name, tag, v):
    f = out / f"{name}.{tag}.v{v}.json"
    return json.loads(f.read_text())["mean"] if f.exists() else None
names = sorted({f.name.split(".")[0] for f in out.glob("*.v*.json")})
print("| scene | " + " | ".join(f"{v} views: PSNR / SSIM, s/view" for v in views)
      + " | base at 4 / its best (views) | plane sweep SSIM at " + ", ".join(views) + " |")
print("|---|" + "---|" * len(views) + "---|---|")
checks, real8, base4 = [], [], []
for n in names:
    m = {v: load(n, "model", v) for v in views}
    b = {v: load(n, "base", v) for v in views}
    row = [n] + [f"{x['psnr']:.2f} / {x['ssim']:.3f}, {x['seconds']:.2f}" if x else "-" for x in m.values()]
    bb = {v: x for v, x in b.items() if x}
    if bb:
        best = max(bb, key=lambda v: bb[v]["psnr"])
        row.append(f"{bb['4']['psnr']:.2f} / {bb[best]['psnr']:.2f} ({best})" if "4" in bb else "-")
    else:
        row.append("-")
    row.append(", ".join(f"{x['baselines']['plane_sweep']['ssim']:.3f}" if x else "-" for x in m.values()))
    print("| " + " | ".join(row) + " |")
    if all(m.values()):
        p = {v: m[v]["psnr"] for v in views}
        checks.append((n, "8 views >= 4 + 0.3 dB", p["8"] - p["4"] >= 0.3, p["8"] - p["4"]))
        checks.append((n, "10 views >= 8", p["10"] >= p["8"], p["10"] - p["8"]))
        worst = min(m[v]["ssim"] - m[v]["baselines"]["plane_sweep"]["ssim"] for v in views)
        checks.append((n, "SSIM above the plane sweep's", worst > 0, worst))
        if bb and not n.startswith("procedural"):
            checks.append((n, "8 views >= base's best - 0.2 dB", p["8"] >= bb[best]["psnr"] - 0.2, p["8"] - bb[best]["psnr"]))
            if "4" in bb:
                real8.append(p["8"]); base4.append(bb["4"]["psnr"])
        if bb and n.startswith("procedural") and "4" in bb:
            checks.append((n, "procedural: 4 views not worse than the base's", p["4"] >= bb["4"]["psnr"] - 0.05, p["4"] - bb["4"]["psnr"]))
if real8:
    gain = sum(real8) / len(real8) - sum(base4) / len(base4)
    checks.append(("mean of the real scenes", "8 views >= base at 4 + 1.0 dB", gain >= 1.0, gain))
print()
for n, what, ok, by in checks:
    print(f"- {'ok' if ok else 'FAIL'} {n}: {what} ({by:+.2f})")
PY
