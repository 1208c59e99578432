//! `--holdout` / `--llffhold`: the views a command holds out. A held-out view is never a
//! source (and, for `tune`, never a target, its image never read).

use crate::rendering::holdout_list;
use anyhow::{bail, Result};
use clap::Args;

/// Which views are held out: shared by `eval`, `report`, `tune` and `mpi`.
#[derive(Debug, Clone, Args)]
pub struct HoldoutArgs {
    /// Held-out view indices, comma-separated.
    #[arg(long)]
    pub holdout: Option<String>,
    /// Hold out every Nth view (LLFF's convention: 0, N, 2N, ...).
    #[arg(long, conflicts_with = "holdout")]
    pub llffhold: Option<usize>,
}

impl HoldoutArgs {
    /// The held-out views of a scene of `n` views, checked to be in range; empty when
    /// neither option is given.
    pub fn list(&self, n: usize) -> Result<Vec<usize>> {
        if self.holdout.is_none() && self.llffhold.is_none() {
            return Ok(Vec::new());
        }
        let held = holdout_list(self.holdout.as_deref(), self.llffhold, n)?;
        if let Some(&bad) = held.iter().find(|&&i| i >= n) {
            bail!("held-out view {bad} is out of range: the scene has {n} views");
        }
        let mut distinct = held.clone();
        distinct.sort_unstable();
        distinct.dedup();
        if distinct.len() >= n {
            bail!(
                "{} holds out every one of the scene's {n} views: none is left to render \
                 from (the field's protocol is --llffhold 8)",
                match self.llffhold {
                    Some(k) => format!("--llffhold {k}"),
                    None => "--holdout".to_string(),
                }
            );
        }
        Ok(held)
    }

    /// [`Self::list`], required: an error naming `what` when neither option is given.
    pub fn required(&self, n: usize, what: &str) -> Result<Vec<usize>> {
        let held = self.list(n)?;
        if held.is_empty() {
            bail!("{what} needs held-out views: pass --llffhold N or --holdout I,J,...");
        }
        Ok(held)
    }
}
