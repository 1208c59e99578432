//! `deepstereo poses`: camera poses for a folder of photographs, by COLMAP.
//!
//! Runs COLMAP's feature extraction (SIFT on the CPU, images at most `--max-size` pixels
//! on the longer side for the features only), matching (`--matcher exhaustive` or
//! `sequential`) and mapping, then writes a COLMAP scene that every command reads:
//!
//! ```text
//! SCENE/images/        the registered photographs, copied unchanged
//! SCENE/sparse/0/      cameras.txt, images.txt, points3D.txt (COLMAP text model)
//! SCENE/colmap.log     COLMAP's full output, stage by stage
//! ```
//!
//! One camera (`--camera-model`, default SIMPLE_RADIAL) is shared by all images, at the
//! images' resolution. When the mapper finds several disconnected models the largest is
//! used and the images of the others are named in a warning; images that did not register
//! are named in a warning and left out. `--masks DIR` gives COLMAP feature masks
//! (`poses/masks.rs`). Everything is built in a temporary directory beside `--out` and
//! renamed into place at the end, so a failure leaves nothing behind.

mod masks;

use crate::cmd::support::colmap_run::{log_tail, model_dirs, registered_names, Colmap, Matcher};
use anyhow::{bail, Context};
use deepstereo_core::scene::{image_size, LoadOptions, Scene};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Fewest images a scene can be posed from.
pub const MIN_IMAGES: usize = 3;
/// Image file extensions read (case-insensitive).
pub const IMAGE_EXTENSIONS: [&str; 3] = ["jpg", "jpeg", "png"];

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Folder of photographs (.jpg, .jpeg, .png; sub-folders are not read).
    #[arg(long)]
    pub images: PathBuf,
    /// Scene directory to create (must not exist).
    #[arg(long)]
    pub out: PathBuf,
    /// COLMAP binary (default: $COLMAP, else `colmap` on the PATH).
    #[arg(long)]
    pub colmap: Option<PathBuf>,
    /// Image pairs to match: exhaustive (every pair; small sets) or sequential (each image
    /// with the next ones in name order; video frames).
    #[arg(long, value_parser = super::args::choice::<Matcher>(), default_value = "exhaustive")]
    pub matcher: Matcher,
    /// Longer image side, in pixels, that features are extracted at (the scene keeps the
    /// full-resolution images and cameras).
    #[arg(long, default_value_t = 1000)]
    pub max_size: u32,
    /// COLMAP camera model shared by all images: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
    /// RADIAL or OPENCV.
    #[arg(long, default_value = "SIMPLE_RADIAL")]
    pub camera_model: String,
    /// Least triangulation angle (degrees) of the pair the reconstruction starts from;
    /// smaller values admit forward-facing, small-baseline captures (COLMAP's default 16).
    #[arg(long, default_value_t = 4.0)]
    pub init_tri_angle: f64,
    /// Known focal length in pixels of the images (fixed, not refined); the principal
    /// point is the image centre. Without it COLMAP estimates the focal length, which
    /// small or object-centred sets can get wrong.
    #[arg(long)]
    pub focal: Option<f64>,
    /// Threads COLMAP may use (default: the machine's cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Folder of feature masks, one PNG per photograph of its size (for `a.jpg`,
    /// `a.jpg.png` as COLMAP names it, or `a.png`): no features where a mask is black.
    /// Mask what moves: people, cars, or the room around a turntable's turning object.
    #[arg(long)]
    pub masks: Option<PathBuf>,
}

const CAMERA_MODELS: [&str; 5] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
];

pub fn run(args: Args) -> anyhow::Result<()> {
    if !CAMERA_MODELS.contains(&args.camera_model.as_str()) {
        bail!(
            "--camera-model {}: expected one of {}",
            args.camera_model,
            CAMERA_MODELS.join(", ")
        );
    }
    if !(args.init_tri_angle > 0.0 && args.init_tri_angle < 90.0) {
        bail!("--init-tri-angle must be between 0 and 90 degrees");
    }
    if args.focal.is_some_and(|f| !(f.is_finite() && f > 0.0)) {
        bail!("--focal must be a positive number of pixels");
    }
    if args.max_size == 0 {
        bail!("--max-size must be positive");
    }
    let images = list_images(&args.images)?;
    let masks = match &args.masks {
        Some(dir) => Some(masks::find_masks(dir, &images)?),
        None => None,
    };
    if args.out.exists() {
        bail!(
            "{}: already exists (choose a new --out)",
            args.out.display()
        );
    }
    let tmp = temp_beside(&args.out)?;
    let result = build(&args, &images, masks.as_deref(), &tmp);
    match result {
        Ok(()) => std::fs::rename(&tmp, &args.out).with_context(|| {
            let _ = std::fs::remove_dir_all(&tmp);
            format!("cannot move the scene to {}", args.out.display())
        }),
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            Err(e)
        }
    }
}

/// The photographs of `dir`, sorted, each with a readable header.
fn list_images(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        bail!(
            "{}: not a directory (--images takes a folder of photographs)",
            dir.display()
        );
    }
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("{}: cannot list", dir.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    out.sort();
    if out.is_empty() {
        bail!(
            "{}: no images (.jpg, .jpeg or .png) in this folder",
            dir.display()
        );
    }
    if out.len() < MIN_IMAGES {
        bail!(
            "{}: {} image(s); at least {MIN_IMAGES} are needed to find poses",
            dir.display(),
            out.len()
        );
    }
    for p in &out {
        image_size(p)?;
    }
    Ok(out)
}

/// COLMAP's parameter list for `model` with focal length `f`, the principal point at the
/// centre of a `w x h` image and no distortion.
fn camera_params(model: &str, f: f64, w: u32, h: u32) -> String {
    let (cx, cy) = (0.5 * w as f64, 0.5 * h as f64);
    let v: Vec<f64> = match model {
        "PINHOLE" => vec![f, f, cx, cy],
        "SIMPLE_RADIAL" => vec![f, cx, cy, 0.0],
        "RADIAL" => vec![f, cx, cy, 0.0, 0.0],
        "OPENCV" => vec![f, f, cx, cy, 0.0, 0.0, 0.0, 0.0],
        _ => vec![f, cx, cy],
    };
    v.iter()
        .map(|x| x.to_string())
        .collect::<Vec<_>>()
        .join(",")
}

/// A fresh temporary directory next to `out` (same file system, so the final rename is
/// atomic).
fn temp_beside(out: &Path) -> anyhow::Result<PathBuf> {
    let parent = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).with_context(|| parent.display().to_string())?;
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into());
    let tmp = parent.join(format!(".{name}.poses-{}.tmp", std::process::id()));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).with_context(|| tmp.display().to_string())?;
    }
    std::fs::create_dir(&tmp).with_context(|| tmp.display().to_string())?;
    Ok(tmp)
}

fn spinner(msg: String) -> ProgressBar {
    let pb = ProgressBar::new_spinner();
    pb.set_style(
        ProgressStyle::with_template("{spinner} {msg} ({elapsed})")
            .unwrap_or_else(|_| ProgressStyle::default_spinner()),
    );
    pb.enable_steady_tick(Duration::from_millis(200));
    pb.set_message(msg);
    pb
}

/// Runs one stage under a spinner and prints how long it took.
fn stage<T>(n: usize, name: &str, f: impl FnOnce() -> anyhow::Result<T>) -> anyhow::Result<T> {
    let t0 = Instant::now();
    let pb = spinner(format!("[{n}/5] {name}"));
    let r = f();
    pb.finish_and_clear();
    if r.is_ok() {
        eprintln!("[{n}/5] {name}: {:.1} s", t0.elapsed().as_secs_f64());
    }
    r
}

/// The photographs into `img_dir` and, with `masks`, their masks into `mask_dir`.
fn copy_inputs(
    images: &[PathBuf],
    masks: Option<&[PathBuf]>,
    (img_dir, mask_dir): (&Path, &Path),
) -> anyhow::Result<()> {
    std::fs::create_dir(img_dir).with_context(|| img_dir.display().to_string())?;
    for p in images {
        let name = p.file_name().context("image without a file name")?;
        std::fs::copy(p, img_dir.join(name))
            .with_context(|| format!("cannot copy {}", p.display()))?;
    }
    if let Some(m) = masks {
        masks::copy_masks(m, images, mask_dir)?;
    }
    Ok(())
}

/// Removes COLMAP's scratch file or directory `p`, if it is there (best effort).
fn remove_scratch(p: &Path) {
    let _ = if p.is_dir() {
        std::fs::remove_dir_all(p)
    } else {
        std::fs::remove_file(p)
    };
}

fn build(
    args: &Args,
    images: &[PathBuf],
    masks: Option<&[PathBuf]>,
    tmp: &Path,
) -> anyhow::Result<()> {
    let colmap = colmap_of(args, tmp);
    colmap.check()?;
    let img_dir = tmp.join("images");
    let (db, work) = (tmp.join("database.db"), tmp.join("mapper"));
    let mask_dir = tmp.join("masks");
    stage(1, "copying images", || {
        copy_inputs(images, masks, (&img_dir, &mask_dir))
    })?;
    let params = match args.focal {
        Some(f) => {
            let (w, h) = image_size(&images[0])?;
            Some(camera_params(&args.camera_model, f, w, h))
        }
        None => None,
    };
    stage(2, "feature extraction", || {
        colmap.extract(
            &db,
            &img_dir,
            &args.camera_model,
            params.as_deref(),
            args.max_size,
            masks.is_some().then_some(mask_dir.as_path()),
        )
    })?;
    stage(3, "matching", || colmap.do_match(&db, args.matcher))?;
    stage(4, "mapping", || {
        let mapped = colmap.map(
            &db,
            &img_dir,
            &work,
            args.init_tri_angle,
            args.focal.is_none(),
        );
        match (mapped, &args.masks) {
            (Err(e), Some(dir)) => Err(e.context(format!(
                "with --masks {}: black mask pixels get no features; check that the masks \
                 are white where the photographs should be used",
                dir.display()
            ))),
            (r, _) => r,
        }
    })?;
    let sparse = tmp.join("sparse").join("0");
    let names = stage(5, "writing the model", || {
        choose_model(&colmap, &work, &sparse, images.len())
    })?;
    drop_unregistered(images, &names, &img_dir);
    for p in [&db, &work, &mask_dir] {
        remove_scratch(p);
    }
    let scene = Scene::load(tmp, &LoadOptions::default())
        .context("the scene COLMAP made cannot be read back")?;
    eprintln!(
        "{} views posed; depth bounds {:.3} .. {:.3} (from {} COLMAP points); COLMAP's log: {}",
        scene.views.len(),
        scene.near,
        scene.far,
        scene.points.len(),
        args.out.join("colmap.log").display()
    );
    Ok(())
}

/// The COLMAP to run: `--colmap`, else `$COLMAP`, else `colmap` on the PATH, with
/// `--threads` (default: every core), logging to `tmp/colmap.log`.
fn colmap_of(args: &Args, tmp: &Path) -> Colmap {
    let binary = args
        .colmap
        .clone()
        .or_else(|| std::env::var_os("COLMAP").map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from("colmap"));
    Colmap {
        binary,
        threads: args
            .threads
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())),
        log: tmp.join("colmap.log"),
    }
}

/// Names, with a warning, the images COLMAP did not register (not in `names`) and
/// removes their copies from `img_dir`.
fn drop_unregistered(images: &[PathBuf], names: &[String], img_dir: &Path) {
    let all: Vec<String> = images
        .iter()
        .filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .collect();
    let missing: Vec<&String> = all.iter().filter(|n| !names.contains(n)).collect();
    if !missing.is_empty() {
        eprintln!(
            "warning: {} of {} images did not register and are left out: {}",
            missing.len(),
            all.len(),
            missing
                .iter()
                .map(|s| s.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
        for n in &missing {
            let _ = std::fs::remove_file(img_dir.join(n));
        }
    }
}

/// Converts the mapper's largest model to text in `sparse` and returns its image names;
/// fails when there is none or it has too few images.
fn choose_model(
    colmap: &Colmap,
    work: &Path,
    sparse: &Path,
    total: usize,
) -> anyhow::Result<Vec<String>> {
    let models = model_dirs(work);
    if models.is_empty() {
        bail!(
            "COLMAP could not reconstruct any camera: too few features matched between the \
             images (untextured surfaces such as a plain wall, too little overlap, or too \
             few images). The end of COLMAP's log:\n{}",
            log_tail(&colmap.log)
        );
    }
    let mut best: Option<(usize, Vec<String>)> = None;
    let mut sizes = Vec::new();
    for (i, m) in models.iter().enumerate() {
        let text = work.join(format!("text_{i}"));
        colmap.to_text(m, &text)?;
        let names = registered_names(&text.join("images.txt"))?;
        sizes.push(names.len());
        if best.as_ref().is_none_or(|(_, b)| names.len() > b.len()) {
            best = Some((i, names));
        }
    }
    let (chosen, names) = best.context("no model")?;
    if models.len() > 1 {
        eprintln!(
            "warning: COLMAP found {} disconnected models ({} images); using the largest, \
             with {} of {total} images; the images of the others are left out",
            models.len(),
            sizes
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>()
                .join(", "),
            names.len()
        );
    }
    if names.len() < MIN_IMAGES {
        bail!(
            "COLMAP registered only {} of {total} images (at least {MIN_IMAGES} needed): too \
             few matches (untextured or repetitive surfaces, too little overlap)",
            names.len()
        );
    }
    let parent = sparse.parent().context("model path")?;
    std::fs::create_dir_all(parent).with_context(|| parent.display().to_string())?;
    std::fs::rename(work.join(format!("text_{chosen}")), sparse)
        .with_context(|| format!("cannot move the model to {}", sparse.display()))?;
    Ok(names)
}
