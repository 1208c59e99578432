//! Weighting the real training scenes (`train --scene-weights`): a scene named in the
//! list is drawn that many times as often as an unnamed one (weight 1) of its pool (real
//! scenes; the procedural ones keep their share, `--synthetic-percent`). A scene is named
//! by its directory's last component (`../shared/data/train/maryrose` is `maryrose`).

use anyhow::bail;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Largest weight: a scene drawn a million times as often as another is a typo.
pub const MAX_SCENE_WEIGHT: f64 = 1e6;

/// Scene names and their weights; empty: every scene equally likely (runs before it).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneWeights(pub Vec<(String, f64)>);

impl SceneWeights {
    /// Parses `NAME=W[,NAME=W...]`.
    pub fn parse(s: &str) -> anyhow::Result<Self> {
        let mut out = Vec::new();
        for item in s.split(',').map(str::trim).filter(|t| !t.is_empty()) {
            let Some((name, w)) = item.split_once('=') else {
                bail!("--scene-weights '{s}': '{item}' is not NAME=WEIGHT");
            };
            let w: f64 = w.trim().parse().map_err(|_| {
                anyhow::anyhow!("--scene-weights '{s}': '{w}' (for {name}) is not a number")
            })?;
            out.push((name.trim().to_string(), w));
        }
        if out.is_empty() {
            bail!("--scene-weights '{s}': expected NAME=WEIGHT[,NAME=WEIGHT...]");
        }
        let weights = Self(out);
        weights.check()?;
        Ok(weights)
    }

    /// Every weight positive and finite, every name given once.
    pub fn check(&self) -> anyhow::Result<()> {
        for (i, (name, w)) in self.0.iter().enumerate() {
            if name.is_empty() {
                bail!("--scene-weights: a weight ({w}) has no scene name");
            }
            if !w.is_finite() || *w <= 0.0 || *w > MAX_SCENE_WEIGHT {
                bail!("--scene-weights: the weight of {name} must be above 0 and at most {MAX_SCENE_WEIGHT}, got {w}");
            }
            if self.0[..i].iter().any(|(n, _)| n == name) {
                bail!("--scene-weights: {name} is given twice");
            }
        }
        Ok(())
    }

    /// Every name must be one of the scene directories `dirs` (as `scene_dirs` lists them).
    pub fn check_names(&self, dirs: &[PathBuf]) -> anyhow::Result<()> {
        let names: Vec<&str> = dirs.iter().filter_map(|d| dir_name(d)).collect();
        for (name, _) in &self.0 {
            if !names.contains(&name.as_str()) {
                bail!(
                    "--scene-weights: no training scene is named {name} (the scenes: {})",
                    names.join(", ")
                );
            }
        }
        Ok(())
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The weight of the scene loaded from `dir` (1 when not named).
    pub fn weight(&self, dir: &str) -> f64 {
        let name = dir_name(Path::new(dir));
        (self.0.iter())
            .find(|(n, _)| Some(n.as_str()) == name)
            .map_or(1.0, |(_, w)| *w)
    }

    /// Index into `weights` drawn with probability proportional to each (`r`: 64 random
    /// bits). `weights` must be non-empty and positive.
    pub fn draw(weights: &[f64], r: u64) -> usize {
        let total: f64 = weights.iter().sum();
        let mut u = (r >> 11) as f64 / (1u64 << 53) as f64 * total;
        for (i, w) in weights.iter().enumerate() {
            if u < *w {
                return i;
            }
            u -= w;
        }
        weights.len() - 1
    }
}

/// The last component of a scene directory, as UTF-8.
fn dir_name(dir: &Path) -> Option<&str> {
    dir.file_name().and_then(|n| n.to_str())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_refuses_bad_lists_by_name() {
        let w = SceneWeights::parse("maryrose=3, milk=0.5").unwrap();
        assert_eq!(w.0, vec![("maryrose".into(), 3.0), ("milk".into(), 0.5)]);
        assert_eq!(w.weight("../data/train/maryrose"), 3.0);
        assert_eq!(w.weight("../data/train/bird"), 1.0);
        for (bad, says) in [
            ("maryrose", "not NAME=WEIGHT"),
            ("maryrose=x", "is not a number"),
            ("maryrose=0", "must be above 0"),
            ("maryrose=-1", "must be above 0"),
            ("maryrose=NaN", "must be above 0"),
            ("maryrose=inf", "must be above 0"),
            ("=2", "has no scene name"),
            ("a=1,a=2", "given twice"),
            (",", "expected NAME=WEIGHT"),
        ] {
            let e = SceneWeights::parse(bad).unwrap_err().to_string();
            assert!(e.contains(says), "{bad}: {e}");
        }
        let dirs = [PathBuf::from("/d/maryrose"), PathBuf::from("/d/bird")];
        w.check_names(&dirs[..1]).unwrap_err();
        let e = SceneWeights::parse("mary=2")
            .unwrap()
            .check_names(&dirs)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no training scene is named mary") && e.contains("maryrose, bird"));
    }

    #[test]
    fn draws_in_proportion_to_the_weights() {
        let weights = [1.0, 3.0, 0.5, 0.5];
        let mut counts = [0usize; 4];
        let n = 200_000u64;
        for k in 0..n {
            counts[SceneWeights::draw(&weights, crate::training::data::mix(k))] += 1;
        }
        for (c, w) in counts.iter().zip(weights) {
            let expected = n as f64 * w / 5.0;
            // Binomial standard deviation at most sqrt(n / 4) = 224: 5 of them.
            assert!((*c as f64 - expected).abs() < 1120.0, "{counts:?}");
        }
        assert_eq!(SceneWeights::draw(&[2.0], u64::MAX), 0);
    }
}
