//! Running the COLMAP binary (feature extraction, matching, mapping, conversion to text)
//! for `deepstereo poses`, and reading back what it made.
//!
//! Every stage runs headless (`QT_QPA_PLATFORM=offscreen`), on the CPU, with a given
//! number of threads; its stdout and stderr are appended to one log file.

use anyhow::{bail, Context};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// Lines of COLMAP's log quoted in an error when a stage fails.
pub const LOG_TAIL_LINES: usize = 12;

/// How to run COLMAP.
#[derive(Clone, Debug)]
pub struct Colmap {
    pub binary: PathBuf,
    pub threads: usize,
    pub log: PathBuf,
}

/// How images are matched.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Matcher {
    /// Every pair (small sets).
    Exhaustive,
    /// Each image with the next few in name order (video-like sets).
    Sequential,
}

impl Matcher {
    fn command(self) -> &'static str {
        match self {
            Matcher::Exhaustive => "exhaustive_matcher",
            Matcher::Sequential => "sequential_matcher",
        }
    }
}

/// The message for a COLMAP binary that cannot be started.
pub fn missing_message(binary: &Path, err: &std::io::Error) -> String {
    format!(
        "cannot run COLMAP ('{}': {err}): install it (Debian/Ubuntu: apt-get install colmap) \
         or pass --colmap PATH (or set COLMAP=PATH)",
        binary.display()
    )
}

impl Colmap {
    /// Checks that the binary starts (`colmap help`).
    pub fn check(&self) -> anyhow::Result<()> {
        let out = Command::new(&self.binary)
            .arg("help")
            .env("QT_QPA_PLATFORM", "offscreen")
            .stdin(Stdio::null())
            .output()
            .map_err(|e| anyhow::anyhow!(missing_message(&self.binary, &e)))?;
        let text = String::from_utf8_lossy(&out.stdout);
        if !text.contains("COLMAP") && !String::from_utf8_lossy(&out.stderr).contains("COLMAP") {
            bail!(
                "'{}' does not look like COLMAP (its 'help' does not mention COLMAP)",
                self.binary.display()
            );
        }
        Ok(())
    }

    /// Runs `colmap <command> <args>`, appending its output to the log; an error quoting
    /// the log's tail when it fails.
    pub fn run(&self, stage: &str, command: &str, args: &[String]) -> anyhow::Result<()> {
        let mut log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .with_context(|| format!("{}: cannot open the log", self.log.display()))?;
        writeln!(log, "\n===== {stage}: colmap {command} {}", args.join(" "))?;
        let err_log = log.try_clone()?;
        let status = Command::new(&self.binary)
            .arg(command)
            .args(args)
            .env("QT_QPA_PLATFORM", "offscreen")
            .stdin(Stdio::null())
            .stdout(Stdio::from(log))
            .stderr(Stdio::from(err_log))
            .status()
            .map_err(|e| anyhow::anyhow!(missing_message(&self.binary, &e)))?;
        if !status.success() {
            bail!(
                "COLMAP {stage} ({command}) failed ({status}); the end of its log:\n{}",
                log_tail(&self.log)
            );
        }
        Ok(())
    }

    fn threads(&self) -> String {
        self.threads.max(1).to_string()
    }

    /// SIFT features of every image of `images` into `database`, one camera shared by all
    /// images, at most `max_size` pixels on the longer side.
    /// `camera_params` (COLMAP's comma-separated list for the model), when given, is the
    /// camera's starting point instead of COLMAP's guess; `masks`, when given, holds
    /// `<image name>.png` feature masks (`ImageReader.mask_path`).
    pub fn extract(
        &self,
        database: &Path,
        images: &Path,
        camera_model: &str,
        camera_params: Option<&str>,
        max_size: u32,
        masks: Option<&Path>,
    ) -> anyhow::Result<()> {
        let mut args = vec![
            "--database_path".into(),
            path_arg(database),
            "--image_path".into(),
            path_arg(images),
            "--ImageReader.single_camera".into(),
            "1".into(),
            "--ImageReader.camera_model".into(),
            camera_model.into(),
            "--SiftExtraction.use_gpu".into(),
            "0".into(),
            "--SiftExtraction.num_threads".into(),
            self.threads(),
            "--SiftExtraction.max_image_size".into(),
            max_size.to_string(),
        ];
        if let Some(p) = camera_params {
            args.extend(["--ImageReader.camera_params".into(), p.to_string()]);
        }
        if let Some(m) = masks {
            args.extend(["--ImageReader.mask_path".into(), path_arg(m)]);
        }
        self.run("feature extraction", "feature_extractor", &args)
    }

    pub fn do_match(&self, database: &Path, matcher: Matcher) -> anyhow::Result<()> {
        let args = vec![
            "--database_path".into(),
            path_arg(database),
            "--SiftMatching.use_gpu".into(),
            "0".into(),
            "--SiftMatching.num_threads".into(),
            self.threads(),
        ];
        self.run("matching", matcher.command(), &args)
    }

    /// Incremental mapping into `sparse/0`, `sparse/1`, ...; `init_tri_angle` (degrees)
    /// is the least triangulation angle of the initial image pair (COLMAP's default, 16,
    /// refuses small-baseline, forward-facing captures).
    pub fn map(
        &self,
        database: &Path,
        images: &Path,
        sparse: &Path,
        init_tri_angle: f64,
        refine_focal: bool,
    ) -> anyhow::Result<()> {
        std::fs::create_dir_all(sparse).with_context(|| sparse.display().to_string())?;
        let args = vec![
            "--database_path".into(),
            path_arg(database),
            "--image_path".into(),
            path_arg(images),
            "--output_path".into(),
            path_arg(sparse),
            "--Mapper.num_threads".into(),
            self.threads(),
            "--Mapper.init_min_tri_angle".into(),
            init_tri_angle.to_string(),
            "--Mapper.ba_refine_focal_length".into(),
            if refine_focal { "1" } else { "0" }.into(),
        ];
        self.run("mapping", "mapper", &args).map_err(|e| {
            let log = std::fs::read_to_string(&self.log).unwrap_or_default();
            if log.contains("No good initial image pair found") {
                anyhow::anyhow!(
                    "COLMAP could not reconstruct any camera: no image pair has enough \
                     matched features with parallax (untextured surfaces such as a plain \
                     wall, too little overlap or too small a baseline; a forward-facing \
                     capture may need a smaller --init-tri-angle). {e}"
                )
            } else {
                e
            }
        })
    }

    /// Converts a binary model to text in `out`.
    pub fn to_text(&self, model: &Path, out: &Path) -> anyhow::Result<()> {
        std::fs::create_dir_all(out).with_context(|| out.display().to_string())?;
        let args = vec![
            "--input_path".into(),
            path_arg(model),
            "--output_path".into(),
            path_arg(out),
            "--output_type".into(),
            "TXT".into(),
        ];
        self.run("conversion to text", "model_converter", &args)
    }
}

fn path_arg(p: &Path) -> String {
    p.to_string_lossy().into_owned()
}

/// The last [`LOG_TAIL_LINES`] lines of a log (indented), or a note that it is empty.
pub fn log_tail(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    if lines.is_empty() {
        return "  (empty)".into();
    }
    lines[lines.len().saturating_sub(LOG_TAIL_LINES)..]
        .iter()
        .map(|l| format!("  {l}"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// Image names registered in a text model's `images.txt` (every other non-comment line).
pub fn registered_names(images_txt: &Path) -> anyhow::Result<Vec<String>> {
    let text = std::fs::read_to_string(images_txt)
        .with_context(|| format!("{}: cannot read", images_txt.display()))?;
    let mut names = Vec::new();
    let mut header = true;
    for line in text.lines() {
        if line.starts_with('#') {
            continue;
        }
        if header {
            // IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (names may hold spaces).
            let fields: Vec<&str> = line.splitn(10, ' ').collect();
            if fields.len() == 10 {
                names.push(fields[9].trim().to_string());
            } else if !line.trim().is_empty() {
                bail!("{}: malformed image line '{line}'", images_txt.display());
            } else {
                continue;
            }
        }
        header = !header;
    }
    names.sort();
    Ok(names)
}

/// The models COLMAP's mapper wrote under `sparse` (`0/`, `1/`, ...), by number.
pub fn model_dirs(sparse: &Path) -> Vec<PathBuf> {
    let mut dirs: Vec<(u32, PathBuf)> = std::fs::read_dir(sparse)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let p = e.path();
            let n = p.file_name()?.to_str()?.parse::<u32>().ok()?;
            (p.join("images.bin").is_file() || p.join("images.txt").is_file()).then_some((n, p))
        })
        .collect();
    dirs.sort();
    dirs.into_iter().map(|(_, p)| p).collect()
}
