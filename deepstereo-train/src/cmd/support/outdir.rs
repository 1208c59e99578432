//! Output directories that appear whole or not at all: a command writes into a staging
//! directory beside the output and moves its contents into place only when it succeeds;
//! when it fails (an error, or a panic unwinding) the staging directory, and any parent
//! directories made for it, are removed, so a failed command leaves nothing behind.
//!
//! Interrupted runs: every staging directory (and every temporary file registered with
//! [`Pending`]) is listed while it exists, and [`remove_pending`] (called by the SIGINT
//! and SIGTERM handler, [`crate::cmd::support::interrupt`]) removes them before the process exits. A
//! SIGKILL cannot be caught: it leaves `.<name>.partial-<pid>/` beside the output, and the
//! next run into the same output removes those whose process no longer exists.

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// Paths to remove if the process is interrupted: staging directories and temporary files.
static PENDING: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// A path listed for removal on interruption while this guard lives.
#[derive(Debug)]
pub struct Pending(PathBuf);

impl Pending {
    /// Lists `path` (a file or directory this process is writing) for removal on
    /// interruption.
    pub fn new(path: &Path) -> Self {
        if let Ok(mut p) = PENDING.lock() {
            p.push(path.to_path_buf());
        }
        Self(path.to_path_buf())
    }
}

impl Drop for Pending {
    fn drop(&mut self) {
        if let Ok(mut p) = PENDING.lock() {
            if let Some(i) = p.iter().rposition(|q| *q == self.0) {
                p.swap_remove(i);
            }
        }
    }
}

/// Removes every listed staging directory and temporary file (on SIGINT or SIGTERM; the
/// handler runs on a thread of its own, not in the signal's context).
pub fn remove_pending() {
    let paths = PENDING.lock().unwrap_or_else(|e| e.into_inner()).clone();
    for p in paths {
        if p.is_dir() {
            let _ = std::fs::remove_dir_all(&p);
        } else {
            let _ = std::fs::remove_file(&p);
        }
    }
}

/// Whether a process with this id exists (it may be another program now).
fn process_alive(pid: u32) -> bool {
    let Ok(pid) = libc::pid_t::try_from(pid) else {
        return false;
    };
    // SAFETY: kill with signal 0 only checks for the process; it sends nothing.
    let r = unsafe { libc::kill(pid, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// Removes `.<name>.partial-<pid>` entries in `parent` left by processes that no longer
/// exist (a run killed with SIGKILL); returns what it removed.
pub fn remove_stale_stages(parent: &Path, name: &str) -> Vec<PathBuf> {
    let prefix = format!(".{name}.partial-");
    let mut removed = Vec::new();
    let Ok(entries) = std::fs::read_dir(parent) else {
        return removed;
    };
    for e in entries.flatten() {
        let file = e.file_name();
        let Some(pid) = file
            .to_str()
            .and_then(|f| f.strip_prefix(&prefix))
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        if pid != std::process::id() && !process_alive(pid) {
            let path = e.path();
            if std::fs::remove_dir_all(&path).is_ok() {
                removed.push(path);
            }
        }
    }
    removed
}

/// A staged output directory; see the module doc.
#[derive(Debug)]
pub struct StagedDir {
    target: PathBuf,
    stage: PathBuf,
    /// Ancestors created for the stage, deepest first (removed again on failure if empty).
    made: Vec<PathBuf>,
    committed: bool,
    /// Lists the stage for removal on SIGINT or SIGTERM while it exists.
    _pending: Pending,
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
        for stale in remove_stale_stages(parent, &name.to_string_lossy()) {
            eprintln!(
                "note: removed {}, left by an interrupted run",
                stale.display()
            );
        }
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
            _pending: Pending::new(&stage),
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
