//! What `tune` reads and writes: the scene at a resolution its budget allows, and the
//! model file.

use super::*;
use crate::cmd::args::HoldoutArgs;

/// Seconds the prior takes to read one view of a megapixel at 32 planes, an upper bound:
/// 22-25 s measured on the 2-core VM with a training run beside it (commit `4a876fd`).
pub(super) const SECONDS_PER_MEGAPIXEL: f64 = 30.0;

/// The largest share of a time budget one view's read may take: beyond it the scene is
/// read at a lower resolution.
pub(super) const MAX_VIEW_SHARE: f64 = 0.25;

pub(super) fn seconds_budget(b: Budget) -> Option<f64> {
    match b {
        Budget::Seconds(s) => Some(s),
        Budget::Steps(_) => None,
    }
}

/// The scene without its held-out views, and their indices in the full scene: at the
/// working resolution (or `--downscale`'s), and with a time budget at most at the
/// resolution where one view's read fits [`MAX_VIEW_SHARE`] of it (said in a note): a
/// budget is kept whatever the images' size.
pub(super) fn load_tuning_scene(
    args: &SceneArgs,
    holdout: &HoldoutArgs,
    budget: Option<f64>,
) -> Result<(Scene, Vec<usize>)> {
    let mut opts = args.working_options();
    loop {
        let mut held = Vec::new();
        let scene = Scene::load_views(&args.scene, &opts, |n| {
            held = holdout.list(n).map_err(|e| e.to_string())?;
            Ok((0..n).filter(|i| !held.contains(i)).collect())
        })?;
        let factor = 1u32 << scene.downscale_levels;
        let megapixels = scene
            .views
            .iter()
            .map(|v| v.camera.intrinsics.width as f64 * v.camera.intrinsics.height as f64)
            .fold(0.0, f64::max)
            / 1e6;
        let view_seconds = megapixels * SECONDS_PER_MEGAPIXEL;
        let over = budget.filter(|b| view_seconds > b * MAX_VIEW_SHARE);
        if let (Some(b), true) = (over, 2 * factor <= MAX_DOWNSCALE) {
            eprintln!(
                "note: at 1/{factor} a view takes about {view_seconds:.0} s to read, over a quarter of the {b:.0} s budget: reading the scene at 1/{} (more --minutes read it finer)",
                2 * factor
            );
            opts.downscale = Some(2 * factor);
            continue;
        }
        for n in &scene.notes {
            eprintln!("note: {n}");
        }
        return Ok((scene, held));
    }
}

/// Refuses an --out that cannot be written, before anything runs.
pub(super) fn check_out(out: &Path) -> Result<()> {
    if out.is_dir() {
        bail!(
            "--out {}: is a directory; name a .safetensors file",
            out.display()
        );
    }
    let dir = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    // Every command creates the missing folders above its outputs (docs/commands.md).
    std::fs::create_dir_all(&dir)
        .with_context(|| format!("--out {}: cannot create {}", out.display(), dir.display()))?;
    let probe = dir.join(format!(".deepstereo-tune-probe.{}", std::process::id()));
    std::fs::write(&probe, b"")
        .with_context(|| format!("--out {}: cannot write in {}", out.display(), dir.display()))?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

/// Writes the weights with the config, the scene prior and the tune's options,
/// atomically.
pub(super) fn save_model(
    out: &Path,
    cfg: &Config,
    varmap: &candle_nn::VarMap,
    prior: Option<&PriorGrid>,
    provenance: &str,
) -> Result<()> {
    let extra = [(TUNE_KEY, provenance.to_string())];
    weights::save_with_prior(out, cfg, varmap, prior, &extra)?;
    Ok(())
}
