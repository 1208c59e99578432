#!/usr/bin/env bash
# The whole test suite, as a fresh machine runs it: Rust tests, then the Python parity
# checks (PyTorch reference and onnxruntime) in a venv that this script creates itself
# from the pinned python/requirements.txt.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"

echo "== cargo fmt / clippy"
cargo fmt --all -- --check
cargo clippy --release --workspace --all-targets -- -D warnings

echo "== Python venv"
VENV="$ROOT/.venv"
STAMP="$VENV/.requirements.sha256"
WANT="$(sha256sum python/requirements.txt | cut -d' ' -f1)"
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$STAMP" 2>/dev/null)" != "$WANT" ]; then
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install --quiet --disable-pip-version-check -r python/requirements.txt
  echo "$WANT" > "$STAMP"
fi

echo "== COLMAP (for tests/poses.rs: deepstereo poses runs the real binary)"
if ! command -v colmap >/dev/null 2>&1; then
  if command -v apt-get >/dev/null 2>&1; then
    SUDO=""
    if [ "$(id -u)" != 0 ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi
    $SUDO apt-get update && $SUDO apt-get install -y colmap
  else
    echo "error: COLMAP is not installed and apt-get is not available to install it;" >&2
    echo "       install COLMAP (https://colmap.github.io/install.html) and put it on the PATH" >&2
    exit 1
  fi
fi
export DEEPSTEREO_REQUIRE_COLMAP=1

echo "== ffmpeg and Chromium (for tests/outputs.rs: path videos checked with ffprobe, report pages in a headless browser)"
MISSING=""
command -v ffmpeg >/dev/null 2>&1 && command -v ffprobe >/dev/null 2>&1 || MISSING="$MISSING ffmpeg"
command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 \
  || command -v google-chrome >/dev/null 2>&1 || MISSING="$MISSING chromium"
if [ -n "$MISSING" ]; then
  SUDO=""
  if [ "$(id -u)" != 0 ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi
  echo "installing:$MISSING"
  # shellcheck disable=SC2086
  if ! { command -v apt-get >/dev/null 2>&1 && $SUDO apt-get update \
      && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $MISSING; }; then
    echo "WARNING: could not install$MISSING (no apt-get, or it failed): the tests that need it" >&2
    echo "         print SKIPPED (videos fall back to the GIF check); install it for the full run" >&2
  fi
fi
# Whatever is present now must work: its tests fail instead of skipping.
if command -v ffmpeg >/dev/null 2>&1 && command -v ffprobe >/dev/null 2>&1; then
  export DEEPSTEREO_REQUIRE_FFMPEG=1
fi
if command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 \
    || command -v google-chrome >/dev/null 2>&1; then
  export DEEPSTEREO_REQUIRE_CHROMIUM=1
fi

echo "== Rust build and tests"
cargo build --release --workspace --bins --examples
cargo test --release --workspace

echo "== Python parity (candle vs PyTorch vs onnxruntime vs ort)"
"$VENV/bin/python" python/parity.py --bin "$ROOT/target/release/deepstereo"

echo "== DDP training (train_ddp.py against candle; torchrun, 2 processes, gloo; resume)"
"$VENV/bin/python" python/ddp_check.py --bin "$ROOT/target/release/deepstereo"
echo "== all tests passed"
