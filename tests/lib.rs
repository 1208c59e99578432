//! Integration tests live in tests/tests/*.rs; they drive the built `deepstereo` binary.
