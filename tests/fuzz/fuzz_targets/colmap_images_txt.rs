#![no_main]
//! cargo-fuzz target `colmap_images_txt` (nightly: `cargo fuzz run colmap_images_txt` in tests/fuzz); the stable
//! driver runs the same function (tests/fuzz/run.sh).

#[path = "../targets.rs"]
mod targets;

static FIXTURE: std::sync::OnceLock<targets::Fixture> = std::sync::OnceLock::new();

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = targets::run("colmap_images_txt", data, FIXTURE.get_or_init(targets::Fixture::new));
});
