//! The learning rate against the step: constant (the default) or a cosine decay over a
//! span of steps, which a resumed run may add or change (the log records the rate used).

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

/// The final rate's share of the initial one when `--lr-final` is not given.
pub const DEFAULT_LR_FINAL: f64 = 0.05;

/// How the learning rate follows the step count.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum LrSchedule {
    /// The initial rate throughout.
    #[default]
    Constant,
    /// `lr` up to step `start`, then `lr * (f + (1 - f) * (1 + cos(pi * x)) / 2)` with
    /// `x = (step - start) / (end - start)` and `f = final_factor`, then `lr * f` after `end`.
    Cosine {
        start: u64,
        end: u64,
        final_factor: f64,
    },
}

impl LrSchedule {
    /// Parses `constant` or `cosine:START-END` (with the final share `final_factor`).
    pub fn parse(s: &str, final_factor: f64) -> Result<Self> {
        if !(final_factor.is_finite() && final_factor > 0.0 && final_factor <= 1.0) {
            bail!("--lr-final must be in (0, 1], got {final_factor}");
        }
        if s == "constant" {
            return Ok(Self::Constant);
        }
        let span = s.strip_prefix("cosine:").with_context(|| {
            format!("--lr-schedule '{s}': expected 'constant' or 'cosine:START-END'")
        })?;
        let (a, b) = span
            .split_once('-')
            .with_context(|| format!("--lr-schedule '{s}': expected cosine:START-END"))?;
        let num = |t: &str| -> Result<u64> {
            t.trim()
                .parse()
                .with_context(|| format!("--lr-schedule '{s}': '{t}' is not a step count"))
        };
        let (start, end) = (num(a)?, num(b)?);
        if end <= start {
            bail!("--lr-schedule '{s}': END must be after START");
        }
        Ok(Self::Cosine {
            start,
            end,
            final_factor,
        })
    }

    /// The rate of the update that follows `done` completed steps, for initial rate `lr`.
    pub fn lr_at(&self, lr: f64, done: u64) -> f64 {
        match *self {
            Self::Constant => lr,
            Self::Cosine {
                start,
                end,
                final_factor: f,
            } => {
                if done <= start {
                    lr
                } else if done >= end {
                    lr * f
                } else {
                    let x = (done - start) as f64 / (end - start) as f64;
                    lr * (f + (1.0 - f) * 0.5 * (1.0 + (std::f64::consts::PI * x).cos()))
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cosine_ends_and_midpoint() {
        let s = LrSchedule::parse("cosine:100-300", 0.1).unwrap();
        assert_eq!(s.lr_at(1.0, 0), 1.0);
        assert_eq!(s.lr_at(1.0, 100), 1.0);
        assert!((s.lr_at(1.0, 200) - 0.55).abs() < 1e-12);
        assert!((s.lr_at(1.0, 300) - 0.1).abs() < 1e-12);
        assert!((s.lr_at(1.0, 10_000) - 0.1).abs() < 1e-12);
        let mut prev = f64::INFINITY;
        for step in 100..=300 {
            let v = s.lr_at(1.0, step);
            assert!(v <= prev);
            prev = v;
        }
    }

    #[test]
    fn bad_specs_are_refused() {
        for bad in [
            "cosine",
            "cosine:5",
            "cosine:5-5",
            "cosine:9-3",
            "linear:1-2",
            "cosine:a-9",
        ] {
            assert!(LrSchedule::parse(bad, 0.1).is_err(), "{bad}");
        }
        assert!(LrSchedule::parse("cosine:1-2", 0.0).is_err());
        assert!(LrSchedule::parse("cosine:1-2", f64::NAN).is_err());
        assert_eq!(
            LrSchedule::parse("constant", 0.5).unwrap(),
            LrSchedule::Constant
        );
    }
}
