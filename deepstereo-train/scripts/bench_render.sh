#!/usr/bin/env bash
# Render time of two models side by side: ROUNDS alternated runs of `deepstereo eval` on
# the first procedural evaluation scene (eval_scenes.sh: 504x378, seed 987654;
# its held-out views 0 and 8, every 8th), VIEWS source views, default pruning; prints the
# seconds per view of each run and the ratio B / A per round and their median
# (python3, stdlib only). Run it with nothing else on the machine.
# Usage: bash deepstereo-train/scripts/bench_render.sh A B [ROUNDS] [VIEWS] [OUT]
set -euo pipefail
cd "$(dirname "$0")/../.."
A="${1:?usage: bench_render.sh A B [ROUNDS] [VIEWS] [OUT]}"
B="${2:?usage: bench_render.sh A B [ROUNDS] [VIEWS] [OUT]}"
ROUNDS="${3:-5}"
VIEWS="${4:-4}"
OUT="${5:-/tmp/deepstereo-bench-render}"
BIN=target/release/deepstereo
mkdir -p "$OUT"
# shellcheck source=eval_scenes.sh
source deepstereo-train/scripts/eval_scenes.sh
procedural_scenes "$OUT" 1
for r in $(seq 1 "$ROUNDS"); do
  for tag in a b; do
    m="$A"; [ "$tag" = b ] && m="$B"
    "$BIN" eval --scene "$OUT/procedural/scene_0000" --llffhold 8 --views "$VIEWS" --model "$m" \
      --json "$OUT/round$r.$tag.json" > /dev/null 2>&1
  done
done
python3 - "$OUT" "$ROUNDS" "$A" "$B" <<'PY'
import json, statistics, sys, pathlib
out, rounds, a, b = pathlib.Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
ratios = []
for r in range(1, rounds + 1):
    sa = json.loads((out / f"round{r}.a.json").read_text())["mean"]["seconds"]
    sb = json.loads((out / f"round{r}.b.json").read_text())["mean"]["seconds"]
    ratios.append(sb / sa)
    print(f"round {r}: A {sa:.2f} s/view, B {sb:.2f} s/view, B / A {sb / sa:.2f}")
print(f"A = {a}\nB = {b}\nB / A: median {statistics.median(ratios):.2f}, range {min(ratios):.2f}-{max(ratios):.2f} over {rounds} rounds")
PY
