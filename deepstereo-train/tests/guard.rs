//! The non-finite guard: an absurd learning rate makes the loss overflow; training skips
//! those steps, stops after a few with a clear message, and every checkpoint it leaves
//! loads (finite weights).

use anyhow::{ensure, Result};
use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_deepstereo");

#[test]
fn exploding_training_stops_cleanly_with_finite_checkpoint() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let out = dir.path().join("run");
    let o = Command::new(BIN)
        .args([
            "train",
            "--synthetic",
            "2",
            "--synth-size",
            "64x48",
            "--synth-views",
            "6",
            "--steps",
            "30",
            "--batch",
            "2",
        ])
        .args([
            "--checkpoint-every",
            "1",
            "--log-every",
            "1",
            "--validate-every",
            "100",
            "--val-scenes",
            "1",
            "--val-batches",
            "1",
        ])
        .args([
            "--no-progress",
            "--optimizer",
            "adagrad",
            "--lr",
            "1e30",
            "--out",
        ])
        .arg(&out)
        .output()?;
    let err = String::from_utf8_lossy(&o.stderr);
    println!("{err}");
    ensure!(!o.status.success(), "training should stop");
    ensure!(
        err.contains("non-finite") && err.contains("training stopped"),
        "unclear message: {err}"
    );
    ensure!(!err.contains("panicked"));
    let model = out.join("model.safetensors");
    let st = deepstereo_core::weights::load(&model, &candle_core::Device::Cpu);
    ensure!(st.is_ok(), "the last checkpoint must load: {:?}", st.err());
    let log = std::fs::read_to_string(out.join("log.jsonl"))?;
    ensure!(
        log.contains("\"skipped\":true"),
        "skipped steps must be logged"
    );
    Ok(())
}
