//! A run's scenes: the training scenes (directories and procedural ones), the validation
//! batches, and the fixed procedural batch of the benchmarks.

use super::scene_weights::SceneWeights;
use super::RunOptions;
use crate::training::data::{
    make_batch, synth_scenes, Batch, Sampling, SceneData, VALIDATION_SALT,
};
use anyhow::{bail, Context, Result};
use deepstereo_core::config::Config;
use deepstereo_core::scene::scene_dirs;
use deepstereo_core::synth::SynthOptions;
use std::path::{Path, PathBuf};

/// The training scenes of a run, in the order the sampler indexes them: the scenes of
/// every `data` directory (sorted within each), then `synthetic` procedural scenes of
/// `seed`. `deepstereo samples` and the trainer share this, so they draw the same samples.
pub fn training_scenes(
    data: &[PathBuf],
    synthetic: usize,
    synth: &SynthOptions,
    seed: u64,
    levels: usize,
) -> Result<Vec<SceneData>> {
    let mut train = Vec::new();
    for dir in data {
        train.extend(load_scene_dirs(dir, levels)?);
    }
    if synthetic > 0 {
        train.extend(synth_scenes(synthetic, seed, synth, levels)?);
    }
    if train.is_empty() {
        bail!("no training scenes: pass --data DIR or --synthetic N");
    }
    Ok(train)
}

/// The procedural scene options of a run.
pub fn synth_options(run: &RunOptions) -> SynthOptions {
    SynthOptions {
        views: run.synth_views,
        width: run.synth_width,
        height: run.synth_height,
        ..SynthOptions::default()
    }
}

/// The validation scenes: procedural ones from the validation seed (when the run has
/// procedural scenes) and those of `--val-data`.
fn validation_scenes(run: &RunOptions) -> Result<Vec<SceneData>> {
    let levels = run.config.levels;
    let mut val = if run.synthetic > 0 {
        synth_scenes(
            run.val_scenes,
            run.seed ^ VALIDATION_SALT,
            &synth_options(run),
            levels,
        )?
    } else {
        Vec::new()
    };
    for dir in &run.val_data {
        val.extend(load_scene_dirs(dir, levels)?);
    }
    Ok(val)
}

/// Loads the scenes of `dir` ([`scene_dirs`]: the scene itself, or the scenes in it).
fn load_scene_dirs(dir: &Path, levels: usize) -> Result<Vec<SceneData>> {
    scene_dirs(dir)?
        .iter()
        .map(|d| SceneData::load(d, levels).with_context(|| format!("loading {}", d.display())))
        .collect()
}

/// Every --data directory holds scenes, and every name --scene-weights gives is one of
/// them: checked before anything is written or loaded (the scenes load slowly).
pub fn check_data(data: &[PathBuf], weights: Option<&SceneWeights>) -> Result<()> {
    let mut dirs = Vec::new();
    for dir in data {
        dirs.extend(scene_dirs(dir)?);
    }
    if let Some(w) = weights {
        w.check_names(&dirs)?;
    }
    Ok(())
}

/// The training scenes and the validation batches (the config's views, no augmentation,
/// every validation scene alike; the training scenes' when there are no validation
/// scenes). The batches are made once, and the validation scenes are dropped before the
/// training scenes are loaded: they are not needed again, and holding both (all the
/// images' pyramids in f32) raised the default model's run from 7.4 to 11.6 GB (README).
pub(super) fn load_scenes(run: &RunOptions) -> Result<(Vec<SceneData>, Vec<Batch>, usize)> {
    let val_seed = run.seed ^ VALIDATION_SALT;
    let val_sampling = Sampling::fixed(&run.config);
    let batches = |src: &[SceneData]| -> Result<Vec<Batch>> {
        (0..run.val_batches as u64)
            .map(|b| make_batch(&run.config, &val_sampling, src, val_seed, b, run.batch))
            .collect()
    };
    let levels = run.config.levels;
    let synth = synth_options(run);
    let val_scenes = validation_scenes(run)?;
    let n_val = val_scenes.len();
    let val = match val_scenes.is_empty() {
        true => None,
        false => Some(batches(&val_scenes)?),
    };
    drop(val_scenes);
    let train = training_scenes(&run.data, run.synthetic, &synth, run.seed, levels)?;
    let val = match val {
        Some(v) => v,
        None => batches(&train)?,
    };
    Ok((train, val, n_val))
}

/// A batch of `batch` training tiles from 4 procedural scenes of 8 views at 160x120
/// (seed 9): the fixed workload of the network benchmark and the forward probe.
pub fn procedural_batch(cfg: &Config, batch: usize) -> Result<Batch> {
    let opts = SynthOptions {
        views: 8,
        width: 160,
        height: 120,
        ..SynthOptions::default()
    };
    let scenes = synth_scenes(4, 1, &opts, cfg.levels)?;
    make_batch(cfg, &Sampling::fixed(cfg), &scenes, 9, 0, batch)
}
