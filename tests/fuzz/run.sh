#!/usr/bin/env bash
# Fuzzes every reader and the weights/config loader for SECONDS in all (default 300),
# on stable Rust: builds the driver in release mode (sharing the workspace's target
# directory, so the dependencies are reused) and runs the targets of targets.rs under
# its mutation fuzzer. Prints the executions per target; crash inputs are saved under
# tests/fuzz/regressions/<target>/ and replayed by
# `cargo test --release -p deepstereo-core --test fuzz_regressions`.
# Usage: tests/fuzz/run.sh [SECONDS] [TARGET...]
set -euo pipefail
cd "$(dirname "$0")"
SECONDS_TOTAL="${1:-300}"
shift || true
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/../../target}"
cargo build --release --manifest-path driver/Cargo.toml
exec "$CARGO_TARGET_DIR/release/fuzz-driver" "$SECONDS_TOTAL" "$@"
