//! Finding scenes on disk: a scene directory, or a directory of them (such as
//! `deepstereo synth` writes), for the commands and the trainer that take either.

use super::detect;
use crate::error::{Error, Result};
use std::path::{Path, PathBuf};

/// Scene directories under `dir`: `dir` itself when it is a scene, else its immediate
/// subdirectories that are (sorted), e.g. the output of `deepstereo synth`. A directory
/// is a scene when [`detect`] recognises its format.
pub fn scene_dirs(dir: &Path) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        return Err(Error::format(dir, "not a directory"));
    }
    if detect(dir).is_ok() {
        return Ok(vec![dir.to_path_buf()]);
    }
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| Error::format(dir, e.to_string()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir() && detect(p).is_ok())
        .collect();
    out.sort();
    if out.is_empty() {
        return Err(Error::format(
            dir,
            "neither a scene nor a directory of scenes",
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::scene_dirs;
    use std::path::Path;

    /// Makes `dir` look like a NeRF scene to [`super::detect`].
    fn nerf_marker(dir: &Path) {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join("transforms.json"), "{}").unwrap();
    }

    #[test]
    fn a_scene_is_its_own_list() {
        let tmp = tempfile::tempdir().unwrap();
        nerf_marker(tmp.path());
        nerf_marker(&tmp.path().join("inner"));
        assert_eq!(
            scene_dirs(tmp.path()).unwrap(),
            vec![tmp.path().to_path_buf()]
        );
    }

    #[test]
    fn a_directory_of_scenes_lists_them_sorted() {
        let tmp = tempfile::tempdir().unwrap();
        for name in ["scene_0002", "scene_0000", "scene_0001"] {
            nerf_marker(&tmp.path().join(name));
        }
        // Neither a plain folder nor a file counts.
        std::fs::create_dir_all(tmp.path().join("notes")).unwrap();
        std::fs::write(tmp.path().join("transforms.json.bak"), "{}").unwrap();
        let names: Vec<String> = scene_dirs(tmp.path())
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["scene_0000", "scene_0001", "scene_0002"]);
    }

    #[test]
    fn no_scene_and_no_directory_are_errors() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(tmp.path().join("empty")).unwrap();
        let e = scene_dirs(tmp.path()).unwrap_err().to_string();
        assert!(
            e.ends_with(": neither a scene nor a directory of scenes"),
            "{e}"
        );
        let missing = tmp.path().join("missing");
        let e = scene_dirs(&missing).unwrap_err().to_string();
        assert_eq!(e, format!("{}: not a directory", missing.display()));
    }
}
