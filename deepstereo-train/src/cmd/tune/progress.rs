//! `tune`'s progress bar and its plain lines.

use super::*;

pub(super) fn progress_bar(wanted: bool) -> indicatif::ProgressBar {
    if !wanted || !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(1000);
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{bar:30} {percent:>3}%  {msg}  {elapsed} done, {eta} left",
    ) {
        bar.set_style(style);
    }
    bar
}

/// The part of the progress bar a phase fills, from `.0` to `.1` (shares of the whole
/// tune).
#[derive(Clone, Copy, Debug)]
pub(super) struct Span(pub f64, pub f64);

impl Span {
    /// The share of the whole tune at a share `share` of the phase.
    fn at(self, share: f64) -> f64 {
        (self.0 + share.clamp(0.0, 1.0) * (self.1 - self.0)).clamp(0.0, 1.0)
    }
}

fn set_share(bar: &indicatif::ProgressBar, share: f64) {
    bar.set_position((share * 1000.0).round() as u64);
}

pub(super) fn report(bar: &indicatif::ProgressBar, p: &Progress, span: Span) {
    let share = span.at(p.share);
    set_share(bar, share);
    let val = p
        .val_psnr
        .map(|v| format!("  validation {v:.2} dB"))
        .unwrap_or_default();
    bar.set_message(format!(
        "step {}  loss {:.4}{val}  best {:.2} dB",
        p.step, p.loss, p.best_psnr
    ));
    if bar.is_hidden() {
        if let Some(v) = p.val_psnr {
            eprintln!(
                "step {}: loss {:.5}, validation {v:.2} dB (best {:.2}), {:.0}% of the budget",
                p.step,
                p.loss,
                p.best_psnr,
                share * 100.0
            );
        }
    }
}

pub(super) fn report_prior(bar: &indicatif::ProgressBar, p: &PriorProgress, span: Span) {
    set_share(bar, span.at(p.share));
    let (read, total) = p.views;
    let msg = match p.val_psnr {
        Some(v) => format!("scene prior: fitting on {read} views, validation {v:.2} dB"),
        None => format!("scene prior: view {read} of at most {total} read"),
    };
    if bar.is_hidden() {
        eprintln!("{msg}");
    }
    bar.set_message(msg);
}
