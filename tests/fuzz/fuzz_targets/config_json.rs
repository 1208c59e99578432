#![no_main]
//! cargo-fuzz target `config_json` (nightly: `cargo fuzz run config_json` in tests/fuzz); the stable
//! driver runs the same function (tests/fuzz/run.sh).

#[path = "../targets.rs"]
mod targets;

static FIXTURE: std::sync::OnceLock<targets::Fixture> = std::sync::OnceLock::new();

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = targets::run("config_json", data, FIXTURE.get_or_init(targets::Fixture::new));
});
