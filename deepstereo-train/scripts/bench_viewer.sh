#!/usr/bin/env bash
# Frame time of the browser viewer, two viewer pages on one MPI side by side: bakes
# juicebox at view 9 (default options), writes the viewer of git revision REV_A and the
# current one beside copies of it, and opens each ROUNDS times, alternated, in headless
# Chromium with software WebGL (SwiftShader) at `?fit=native&bench=60`; prints each
# run's DEEPSTEREO_BENCH line (read from the console: under --virtual-time-budget the
# page's clock stands still). Run it with nothing else on the machine.
# Usage: bash deepstereo-train/scripts/bench_viewer.sh REV_A [ROUNDS] [OUT]
set -euo pipefail
cd "$(dirname "$0")/../.."
REV_A="${1:?usage: bench_viewer.sh REV_A [ROUNDS] [OUT]}"
ROUNDS="${2:-3}"
OUT="${3:-/tmp/deepstereo-bench-viewer}"
BIN=target/release/deepstereo
DATA="${DATA:-../shared/data}"
BROWSER="$(command -v chromium || command -v chromium-browser || command -v google-chrome)"
rm -rf "$OUT"
mkdir -p "$OUT"
"$BIN" mpi --scene "$DATA/val/juicebox" --target 9 --out "$OUT/b" 2> /dev/null
cp -r "$OUT/b" "$OUT/a"
git show "$REV_A:deepstereo-core/src/mpi/viewer.html" > "$OUT/a/index.html"
run() {
  timeout 60 "$BROWSER" --headless --no-sandbox --disable-dev-shm-usage --use-angle=swiftshader \
    --enable-unsafe-swiftshader --force-device-scale-factor=1 --enable-logging=stderr --v=0 \
    --user-data-dir="$OUT/profile-$1-$2" --window-size=480,270 \
    "file://$(realpath "$OUT/$1")/index.html?fit=native&bench=60" 2>&1 \
    | grep -o 'DEEPSTEREO_BENCH[^"]*' | sed 's/ renderer=.*//' | head -1 || true
}
for r in $(seq 1 "$ROUNDS"); do
  echo "round $r, viewer of $REV_A: $(run a "$r")"
  echo "round $r, current viewer: $(run b "$r")"
done
