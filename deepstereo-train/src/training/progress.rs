//! What a run shows and plots: the progress bar and its log lines, and the curves of
//! `log.jsonl`.

use super::{LogLine, RunOptions, Schedule};
use anyhow::{Context, Result};
use std::path::Path;

/// Shows a log line: as the progress bar's message, and without a bar as a line on
/// standard error with the time left.
pub(super) fn show_line(
    bar: &indicatif::ProgressBar,
    sched: &Schedule,
    run: &RunOptions,
    loss_v: f64,
    line: &LogLine,
) {
    let val = |sep: &str| {
        line.val_psnr
            .map(|p| format!("{sep}val {p:.2} dB"))
            .unwrap_or_default()
    };
    bar.set_message(format!(
        "loss {loss_v:.4}  {:.1} samples/s{}",
        line.samples_per_s,
        val("  ")
    ));
    if !sched.progress {
        let left =
            (sched.steps - line.step) as f64 * run.batch as f64 / line.samples_per_s.max(1e-9);
        eprintln!(
            "step {}/{}: loss {loss_v:.5} ({:.1} samples/s, {} left){}",
            line.step,
            sched.steps,
            line.samples_per_s,
            duration(left),
            val(" ")
        );
    }
}

/// `1h02m`, `3m05s` or `12s`.
fn duration(seconds: f64) -> String {
    let s = seconds.clamp(0.0, 1e9) as u64;
    match (s / 3600, s % 3600 / 60, s % 60) {
        (0, 0, sec) => format!("{sec}s"),
        (0, m, sec) => format!("{m}m{sec:02}s"),
        (h, m, _) => format!("{h}h{m:02}m"),
    }
}

pub(super) fn progress_bar(sched: &Schedule, start: u64) -> indicatif::ProgressBar {
    if !sched.progress {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(sched.steps);
    if let Ok(style) =
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} steps  {msg}  eta {eta}")
    {
        bar.set_style(style);
    }
    bar.set_position(start);
    bar
}

/// Plots a run's training loss and validation PSNR against steps, side by side.
pub fn plot_log(log: &Path, png: &Path) -> Result<()> {
    use deepstereo_core::plot::{plot, Series};
    let text =
        std::fs::read_to_string(log).with_context(|| format!("cannot read {}", log.display()))?;
    let lines: Vec<LogLine> = text
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    let loss: Vec<(f64, f64)> = lines
        .iter()
        .filter_map(|l| l.loss.map(|v| (l.step as f64, v)))
        .collect();
    // Smooth the loss over a window of log lines for readability.
    let k = (loss.len() / 50).max(1);
    let smooth: Vec<(f64, f64)> = loss
        .chunks(k)
        .map(|c| {
            (
                c[c.len() - 1].0,
                c.iter().map(|p| p.1).sum::<f64>() / c.len() as f64,
            )
        })
        .collect();
    let val: Vec<(f64, f64)> = lines
        .iter()
        .filter_map(|l| l.val_psnr.map(|v| (l.step as f64, v)))
        .collect();
    let a = plot(
        "training loss",
        "step",
        "loss",
        &[Series {
            label: "train loss".into(),
            colour: [0.85, 0.2, 0.1],
            points: smooth,
            line: true,
            marker: 0,
            labels: Vec::new(),
        }],
        false,
    );
    let b = plot(
        "validation PSNR (held-out scenes)",
        "step",
        "PSNR dB",
        &[Series {
            label: "validation".into(),
            colour: [0.1, 0.4, 0.85],
            points: val,
            line: true,
            marker: 2,
            labels: Vec::new(),
        }],
        false,
    );
    deepstereo_core::viz::side_by_side(&[&a, &b], 0).save_png(png)?;
    Ok(())
}
