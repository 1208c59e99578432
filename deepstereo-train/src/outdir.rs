//! Output directories that appear whole or not at all: a command writes into a staging
//! directory beside the output and moves its contents into place only when it succeeds;
//! when it fails (an error, or a panic unwinding) the staging directory, and any parent
//! directories made for it, are removed, so a failed command leaves nothing behind.

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};

/// A staged output directory; see the module doc.
#[derive(Debug)]
pub struct StagedDir {
    target: PathBuf,
    stage: PathBuf,
    /// Ancestors created for the stage, deepest first (removed again on failure if empty).
    made: Vec<PathBuf>,
    committed: bool,
}

impl StagedDir {
    /// Prepares to write the directory `target` (which may exist: its other files stay).
    pub fn new(target: &Path) -> Result<Self> {
        if target.exists() && !target.is_dir() {
            bail!("{}: exists and is not a directory", target.display());
        }
        // `.`, `..` or `dir/..` have no name of their own: stage beside what they name.
        let absolute;
        let target = if target.is_dir() && target.file_name().is_none() {
            absolute = target
                .canonicalize()
                .with_context(|| format!("cannot resolve {}", target.display()))?;
            absolute.as_path()
        } else {
            target
        };
        let name = target
            .file_name()
            .with_context(|| format!("{}: not a directory name", target.display()))?;
        let parent = target
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let mut made = Vec::new();
        let mut p = Some(parent);
        while let Some(dir) = p.filter(|d| !d.as_os_str().is_empty() && !d.exists()) {
            made.push(dir.to_path_buf());
            p = dir.parent();
        }
        std::fs::create_dir_all(parent)
            .with_context(|| format!("cannot create {}", parent.display()))?;
        let stage = parent.join(format!(
            ".{}.partial-{}",
            name.to_string_lossy(),
            std::process::id()
        ));
        if stage.exists() {
            std::fs::remove_dir_all(&stage)
                .with_context(|| format!("cannot clear {}", stage.display()))?;
        }
        let staged = Self {
            target: target.to_path_buf(),
            stage,
            made,
            committed: false,
        };
        std::fs::create_dir(&staged.stage)
            .with_context(|| format!("cannot create {}", staged.stage.display()))?;
        Ok(staged)
    }

    /// Where to write the outputs until [`commit`](Self::commit).
    pub fn path(&self) -> &Path {
        &self.stage
    }

    /// The directory the outputs end up in.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Moves the outputs into place.
    pub fn commit(mut self) -> Result<()> {
        if self.target.exists() {
            merge(&self.stage, &self.target)?;
            std::fs::remove_dir_all(&self.stage)
                .with_context(|| format!("cannot remove {}", self.stage.display()))?;
        } else {
            std::fs::rename(&self.stage, &self.target).with_context(|| {
                format!(
                    "cannot move {} to {}",
                    self.stage.display(),
                    self.target.display()
                )
            })?;
        }
        self.committed = true;
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if self.committed {
            return;
        }
        let _ = std::fs::remove_dir_all(&self.stage);
        for dir in &self.made {
            // Only directories made for the stage, and only when nothing else is in them.
            let _ = std::fs::remove_dir(dir);
        }
    }
}

/// Moves every entry of `from` into the existing directory `to`, replacing files of the
/// same name and merging directories.
fn merge(from: &Path, to: &Path) -> Result<()> {
    let entries =
        std::fs::read_dir(from).with_context(|| format!("cannot read {}", from.display()))?;
    for e in entries {
        let e = e.with_context(|| format!("cannot read {}", from.display()))?;
        let (src, dst) = (e.path(), to.join(e.file_name()));
        if src.is_dir() && dst.is_dir() {
            merge(&src, &dst)?;
        } else {
            if dst.is_dir() {
                std::fs::remove_dir_all(&dst)
                    .with_context(|| format!("cannot replace {}", dst.display()))?;
            }
            std::fs::rename(&src, &dst)
                .with_context(|| format!("cannot move {} to {}", src.display(), dst.display()))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dropped_stage_leaves_nothing_and_a_committed_one_merges() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let out = tmp.path().join("a/b/out");
        {
            let s = StagedDir::new(&out).expect("stage");
            std::fs::write(s.path().join("x"), b"1").expect("write");
        }
        assert!(!tmp.path().join("a").exists(), "left behind");
        let s = StagedDir::new(&out).expect("stage");
        std::fs::write(s.path().join("x"), b"1").expect("write");
        s.commit().expect("commit");
        let s = StagedDir::new(&out).expect("stage");
        std::fs::create_dir(s.path().join("sub")).expect("mkdir");
        std::fs::write(s.path().join("sub/y"), b"2").expect("write");
        std::fs::write(s.path().join("x"), b"3").expect("write");
        s.commit().expect("commit");
        assert_eq!(std::fs::read(out.join("x")).expect("x"), b"3");
        assert_eq!(std::fs::read(out.join("sub/y")).expect("y"), b"2");
        let left: Vec<_> = std::fs::read_dir(tmp.path().join("a/b"))
            .expect("dir")
            .collect();
        assert_eq!(left.len(), 1, "only the output remains");
    }
}
