//! Where a scene's files may be: inside the scene directory. A scene file names its images
//! (`transforms.json`'s `file_path`, COLMAP's image names, Middlebury's `*_par.txt`), and
//! an untrusted one could name `../../x.png`, `/abs/x.png`, or an image that is a symbolic
//! link to a file outside: each is refused before it is opened, after resolving `..` and
//! symbolic links, unless the user allows it (`--allow-outside-paths`,
//! [`Within::anywhere`]).
//!
//! Resolving a path stats its existing ancestors but opens nothing: a path outside the
//! scene is never read, whatever it names (a FIFO would block, a device would stream).

use crate::error::{Error, Result};
use std::path::{Component, Path, PathBuf};

/// The directory a scene's files must resolve inside, or none (anywhere).
#[derive(Clone, Debug)]
pub struct Within {
    /// Canonical scene directory; `None`: paths may lead anywhere.
    root: Option<PathBuf>,
}

impl Within {
    /// Files must stay inside `dir` (resolved to its canonical path).
    pub fn scene(dir: &Path) -> Result<Self> {
        let root = dir.canonicalize().map_err(|e| Error::io(dir, e))?;
        Ok(Self { root: Some(root) })
    }

    /// Files may be anywhere (`--allow-outside-paths`).
    pub fn anywhere() -> Self {
        Self { root: None }
    }

    /// Checks that `path`, named by `entry` of the scene file `file`, resolves inside the
    /// scene; the error names the file, the entry and the path.
    pub fn check(&self, file: &Path, entry: &str, path: &Path) -> Result<()> {
        let Some(root) = &self.root else {
            return Ok(());
        };
        let Some(resolved) = resolve(path) else {
            return Err(Error::format(
                path,
                format!(
                    "{}: {entry}: cannot be resolved (a dangling symbolic link, or a folder \
                     that cannot be read); it is not read",
                    file.display()
                ),
            ));
        };
        if resolved.starts_with(root) {
            return Ok(());
        }
        Err(Error::Outside {
            file: file.to_path_buf(),
            entry: entry.to_string(),
            path: path.to_path_buf(),
            root: root.clone(),
        })
    }
}

/// `path` with every symbolic link and `..` resolved: its deepest existing ancestor
/// canonicalized (following links), the rest of its components applied lexically (they
/// name nothing that exists, so no link among them). `None` when it cannot be resolved.
pub fn resolve(path: &Path) -> Option<PathBuf> {
    let abs = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir().ok()?.join(path)
    };
    // Walk up to the deepest ancestor that exists (a dangling link counts as existing:
    // canonicalize then fails and the path is refused).
    let mut base = abs.as_path();
    let mut rest = Vec::new();
    while base.symlink_metadata().is_err() {
        rest.push(base.components().next_back()?);
        base = base.parent()?;
    }
    let mut out = base.canonicalize().ok()?;
    for c in rest.into_iter().rev() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::Normal(n) => out.push(n),
            _ => {}
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_that_leave_the_scene_are_refused_after_links_and_dots() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let scene = tmp.path().join("scene");
        std::fs::create_dir_all(scene.join("images")).expect("mkdir");
        std::fs::write(scene.join("images/a.png"), b"x").expect("write");
        std::fs::write(tmp.path().join("outside.png"), b"x").expect("write");
        std::os::unix::fs::symlink(tmp.path().join("outside.png"), scene.join("images/l.png"))
            .expect("symlink");
        std::os::unix::fs::symlink(scene.join("images/a.png"), scene.join("images/in.png"))
            .expect("symlink");
        let w = Within::scene(&scene).expect("within");
        let f = scene.join("transforms.json");
        let ok = |p: &Path| w.check(&f, "e", p).is_ok();
        assert!(ok(&scene.join("images/a.png")));
        assert!(ok(&scene.join("images/in.png")), "a link inside the scene");
        assert!(ok(&scene.join("images/../images/a.png")));
        assert!(ok(&scene.join("images/missing.png")), "missing but inside");
        assert!(!ok(&scene.join("../outside.png")));
        assert!(!ok(&scene.join("images/../../outside.png")));
        assert!(!ok(&scene.join("images/missing/../../../outside.png")));
        assert!(!ok(&scene.join("nothing/../../outside.png")));
        assert!(ok(&scene.join("nothing/../images/a.png")));
        assert!(!ok(&tmp.path().join("outside.png")), "absolute");
        assert!(!ok(Path::new("/etc/passwd")));
        assert!(!ok(&scene.join("images/l.png")), "a link to outside");
        let msg = w
            .check(&f, "frame 3", &scene.join("../outside.png"))
            .expect_err("outside")
            .to_string();
        assert!(
            msg.contains("transforms.json") && msg.contains("frame 3"),
            "{msg}"
        );
        assert!(msg.contains("--allow-outside-paths"), "{msg}");
        std::os::unix::fs::symlink(scene.join("images/gone.png"), scene.join("images/d.png"))
            .expect("symlink");
        let msg = w
            .check(&f, "frame 4", &scene.join("images/d.png"))
            .expect_err("dangling")
            .to_string();
        assert!(
            msg.contains("dangling") && !msg.contains("outside"),
            "{msg}"
        );
        assert!(Within::anywhere()
            .check(&f, "e", Path::new("/etc/passwd"))
            .is_ok());
    }
}
