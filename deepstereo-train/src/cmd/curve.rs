//! `deepstereo curve`: plot a run's `log.jsonl` (training loss and validation PSNR
//! against steps), as `train` does at the end of a run, at any time (also while it trains).

use crate::training::plot_log;
use anyhow::{bail, Context};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The run's log (`RUN/log.jsonl`), or the run directory.
    #[arg(long)]
    pub log: PathBuf,
    /// The PNG to write (atomically).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let log = if a.log.is_dir() {
        a.log.join("log.jsonl")
    } else {
        a.log.clone()
    };
    let text =
        std::fs::read_to_string(&log).with_context(|| format!("cannot read {}", log.display()))?;
    let parsed = text
        .lines()
        .filter(|l| serde_json::from_str::<crate::training::LogLine>(l).is_ok())
        .count();
    if parsed == 0 {
        bail!(
            "{}: no training log lines (JSON objects with step, loss, lr, ...) in it",
            log.display()
        );
    }
    plot_log(&log, &a.out)?;
    eprintln!("{}: {parsed} log lines plotted", a.out.display());
    Ok(())
}
