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

echo "== Rust build and tests"
cargo build --release --workspace --bins --examples
cargo test --release --workspace

echo "== Python parity (candle vs PyTorch vs onnxruntime vs ort)"
"$VENV/bin/python" python/parity.py --bin "$ROOT/target/release/deepstereo"

echo "== DDP training (train_ddp.py against candle; torchrun, 2 processes, gloo; resume)"
"$VENV/bin/python" python/ddp_check.py --bin "$ROOT/target/release/deepstereo"
echo "== all tests passed"
