//! `deepstereo samples`: the trainer's samples written to disk as numbered safetensors
//! shards, for other trainers (`python/train_ddp.py`, PyTorch DistributedDataParallel).
//!
//! Shard `b` is exactly batch `b` of `deepstereo train` with the same scenes, `--seed`,
//! `--views`, `--augment`, `--synthetic-percent`, `--view-stride` and `--skip-flat`, and
//! `--batch` equal to `--shard-size` (it calls the same sampler, `data::make_batch`, with
//! batch index `b`). Every shard is written atomically; a rerun keeps the shards that are
//! complete (they parse, hold the expected tensors and were made with the same options)
//! and writes the rest.

use super::args::{load_config, size_of, SamplingArgs};
use crate::training::data::{make_batch, Batch, Sampling};
use crate::training::scene_weights::SceneWeights;
use crate::training::{check_data, training_scenes};
use anyhow::{bail, Context};
use deepstereo_core::config::Config;
use deepstereo_core::synth::SynthOptions;
use deepstereo_core::tensorio::{write_safetensors, NamedArray};
use deepstereo_core::weights::CONFIG_KEY;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Metadata key of the format of a shard.
pub const FORMAT_KEY: &str = "format";
/// Value of [`FORMAT_KEY`] in a shard.
pub const SHARD_FORMAT: &str = "deepstereo-samples-v1";
/// Metadata key of the options that made a shard (JSON of [`SampleOptions`]).
pub const OPTIONS_KEY: &str = "deepstereo.samples";
/// Metadata key of the source views of every sample in a shard.
pub const VIEWS_KEY: &str = "views";
/// Metadata key of the shard's index (its batch index in the sampler).
pub const SHARD_KEY: &str = "shard";
/// Metadata key of the number of samples in the shard.
pub const SAMPLES_KEY: &str = "samples";
/// Name of the target tensor in a shard (inputs are `level0..`).
pub const TARGET_NAME: &str = "target";

#[derive(Debug, clap::Args)]
#[command(
    after_help = "Shard b holds batch b of `deepstereo train` with the same scenes, \
--seed, --views, --augment, --synthetic-percent, --view-stride, --skip-flat and --batch = \
--shard-size: tensors `level0..level{L-1}` ([K, D, 4V, H_l, W_l], or [K, D, V, C_v, H_l, W_l] (C_v 4, or 9 with the per-view cue) for the \
any-number-of-views family; for the features family without the F feature channels) and \
`target` ([K, 3, t, t]), f32; for the features family also, per sample k, level l and view \
v its sweep sees, `warp.k.l.v.crop` ([3, h, w], the source crop padded by the CNN's radius), \
`warp.k.l.v.index` ([D*P, 4] i64) and `warp.k.l.v.weight` ([D*P, 4] f32), the bilinear \
taps into the crop's features; metadata `deepstereo.config` \
(the model config JSON), `views` (V, the same for every sample of a shard), `shard`, \
`samples`, `format` = deepstereo-samples-v1 and `deepstereo.samples` (the options). A shard \
is also a valid `deepstereo forward --inputs` file (not for the features family). Shards are written in parallel and \
atomically; rerunning the same command keeps complete shards and writes the missing ones \
(a shard made with other options is an error: choose another --out)."
)]
pub struct Args {
    /// Scene directories (any readable format), or directories of scenes such as
    /// `deepstereo synth` writes. May be repeated and combined with --synthetic.
    #[arg(long, num_args = 1..)]
    pub data: Vec<PathBuf>,
    /// Also generate this many procedural scenes in memory (seeded by --seed).
    #[arg(long, default_value_t = 0)]
    pub synthetic: usize,
    /// Size of procedural scenes' images, WxH.
    #[arg(long, default_value = "160x120")]
    pub synth_size: String,
    /// Views per procedural scene.
    #[arg(long, default_value_t = 10)]
    pub synth_views: usize,
    /// Model config: a preset (`tiny`, `paper`, `nviews`) or a JSON file of a Config.
    #[arg(long, default_value = "tiny")]
    pub config: String,
    /// Total number of samples (the last shard holds the remainder).
    #[arg(long)]
    pub count: usize,
    /// Seed of the samples (and of the procedural scenes), as `train --seed`.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Samples per shard (`train --batch` of the matching candle run).
    #[arg(long, default_value_t = 8)]
    pub shard_size: usize,
    /// Output directory: `shard-00000.safetensors`, `shard-00001.safetensors`, ...
    #[arg(long)]
    pub out: PathBuf,
    /// How samples are drawn.
    #[command(flatten)]
    pub sampling: SamplingArgs,
}

/// What decides a shard's content (stored in every shard; a rerun must match).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampleOptions {
    pub data: Vec<PathBuf>,
    pub synthetic: usize,
    pub synth_width: u32,
    pub synth_height: u32,
    pub synth_views: usize,
    pub views: (usize, usize),
    pub augment: bool,
    pub synthetic_percent: Option<u32>,
    /// Source stride range (shards before it: the nearest views).
    #[serde(default = "nearest_views")]
    pub view_stride: (usize, usize),
    /// Flat-tile threshold (shards before it: every tile).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skip_flat: Option<f32>,
    /// Weights of named real scenes (shards before it: every scene alike).
    #[serde(default, skip_serializing_if = "SceneWeights::is_empty")]
    pub scene_weights: SceneWeights,
    pub seed: u64,
    pub shard_size: usize,
}

fn nearest_views() -> (usize, usize) {
    (1, 1)
}

/// The file name of shard `i`.
pub fn shard_name(i: usize) -> String {
    format!("shard-{i:05}.safetensors")
}

/// Why an existing shard is not kept.
enum Existing {
    Missing,
    Incomplete(String),
    Complete,
}

/// Checks the shard at `path`: it parses, holds every tensor with `samples` samples and
/// was made with `opts` and `cfg` (a complete shard made otherwise is an error).
fn check_shard(
    path: &Path,
    cfg: &Config,
    opts_json: &str,
    cfg_json: &str,
    samples: usize,
) -> anyhow::Result<Existing> {
    if !path.exists() {
        return Ok(Existing::Missing);
    }
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let st = match safetensors::SafeTensors::deserialize(&bytes) {
        Ok(st) => st,
        Err(e) => return Ok(Existing::Incomplete(format!("does not parse ({e})"))),
    };
    let (_, meta) = match safetensors::SafeTensors::read_metadata(&bytes) {
        Ok(m) => m,
        Err(e) => return Ok(Existing::Incomplete(format!("no metadata ({e})"))),
    };
    let m = meta.metadata().clone().unwrap_or_default();
    let same = m.get(OPTIONS_KEY).map(String::as_str) == Some(opts_json)
        && m.get(CONFIG_KEY).map(String::as_str) == Some(cfg_json);
    if !same {
        bail!(
            "{} was written with other options or another config: choose another --out \
             (or delete the shards)",
            path.display()
        );
    }
    let names = (0..cfg.levels)
        .map(deepstereo_export::input_name)
        .chain(std::iter::once(TARGET_NAME.to_string()));
    for name in names {
        match st.tensor(&name) {
            Ok(v)
                if v.dtype() == safetensors::Dtype::F32 && v.shape().first() == Some(&samples) => {}
            Ok(v) => {
                return Ok(Existing::Incomplete(format!(
                    "tensor '{name}' has shape {:?}",
                    v.shape()
                )))
            }
            Err(_) => return Ok(Existing::Incomplete(format!("no tensor '{name}'"))),
        }
    }
    Ok(Existing::Complete)
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let cfg = load_config(&a.config)?;
    cfg.validate().map_err(anyhow::Error::msg)?;
    if a.count == 0 || a.shard_size == 0 {
        bail!("--count and --shard-size must be at least 1");
    }
    let (w, h) = size_of("--synth-size", &a.synth_size)?;
    let sa = &a.sampling;
    let sampling = sampling_of(&a, &cfg)?;
    let opts = SampleOptions {
        data: a.data.clone(),
        synthetic: a.synthetic,
        synth_width: w,
        synth_height: h,
        synth_views: a.synth_views,
        views: sampling.views,
        augment: sa.augment,
        synthetic_percent: sa.synthetic_percent,
        view_stride: sampling.view_stride,
        skip_flat: sa.skip_flat,
        scene_weights: sampling.scene_weights.clone(),
        seed: a.seed,
        shard_size: a.shard_size,
    };
    let opts_json = serde_json::to_string(&opts)?;
    let cfg_json = serde_json::to_string(&cfg)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let shards = a.count.div_ceil(a.shard_size);
    let todo = shards_to_write(&a, &cfg, &opts_json, &cfg_json)?;
    let kept = shards - todo.len();
    if todo.is_empty() {
        eprintln!("all {shards} shards in {} are complete", a.out.display());
        return Ok(());
    }
    let t0 = std::time::Instant::now();
    let synth = SynthOptions {
        views: a.synth_views,
        width: w,
        height: h,
        ..SynthOptions::default()
    };
    let scenes = training_scenes(&a.data, a.synthetic, &synth, a.seed, cfg.levels)?;
    eprintln!(
        "{} scenes ({:.1} s); writing {} of {shards} shards ({kept} complete)",
        scenes.len(),
        t0.elapsed().as_secs_f64(),
        todo.len()
    );
    todo.par_iter().try_for_each(|&i| -> anyhow::Result<()> {
        let b = make_batch(
            &cfg,
            &sampling,
            &scenes,
            a.seed,
            i as u64,
            samples_in(&a, i),
        )?;
        let meta = HashMap::from([
            (CONFIG_KEY.to_string(), cfg_json.clone()),
            (FORMAT_KEY.to_string(), SHARD_FORMAT.to_string()),
            (OPTIONS_KEY.to_string(), opts_json.clone()),
            (VIEWS_KEY.to_string(), b.views.to_string()),
            (SHARD_KEY.to_string(), i.to_string()),
            (SAMPLES_KEY.to_string(), samples_in(&a, i).to_string()),
        ]);
        write_safetensors(&a.out.join(shard_name(i)), &shard_arrays(&b), Some(meta))?;
        Ok(())
    })?;
    let secs = t0.elapsed().as_secs_f64();
    let n: usize = todo.iter().map(|&i| samples_in(&a, i)).sum();
    eprintln!(
        "wrote {} shards ({n} samples) to {} in {secs:.1} s ({:.0} samples/s); {kept} kept",
        todo.len(),
        a.out.display(),
        n as f64 / secs.max(1e-9)
    );
    Ok(())
}

/// How samples are drawn: the sampling options, the config's views and the nearest
/// views by default; checked, with the --scene-weights names against --data's scenes.
fn sampling_of(a: &Args, cfg: &Config) -> anyhow::Result<Sampling> {
    let sa = &a.sampling;
    let sampling = Sampling {
        views: sa.views_range()?.unwrap_or((cfg.views, cfg.views)),
        synthetic_percent: sa.synthetic_percent,
        augment: sa.augment,
        view_stride: sa.view_stride_range()?.unwrap_or((1, 1)),
        skip_flat: sa.skip_flat,
        scene_weights: sa.weights()?.unwrap_or_default(),
        mpi: None,
    };
    sampling.check(cfg)?;
    if !sampling.scene_weights.is_empty() {
        check_data(&a.data, Some(&sampling.scene_weights))?;
    }
    Ok(sampling)
}

/// The shards of `--out` still to write: missing, or incomplete (each named, with why).
fn shards_to_write(
    a: &Args,
    cfg: &Config,
    opts_json: &str,
    cfg_json: &str,
) -> anyhow::Result<Vec<usize>> {
    let mut todo = Vec::new();
    for i in 0..a.count.div_ceil(a.shard_size) {
        let path = a.out.join(shard_name(i));
        match check_shard(&path, cfg, opts_json, cfg_json, samples_in(a, i))? {
            Existing::Complete => {}
            Existing::Missing => todo.push(i),
            Existing::Incomplete(why) => {
                eprintln!("{}: {why}: writing it again", path.display());
                todo.push(i);
            }
        }
    }
    Ok(todo)
}

/// Samples in shard `i` (the last may hold fewer).
fn samples_in(a: &Args, i: usize) -> usize {
    a.shard_size.min(a.count - i * a.shard_size)
}

/// A shard's tensors: the network's inputs per level and the target.
fn shard_arrays(b: &Batch) -> Vec<NamedArray> {
    let mut arrays: Vec<NamedArray> = b
        .levels
        .iter()
        .zip(&b.level_shapes)
        .enumerate()
        .map(|(l, (d, s))| NamedArray::f32(&deepstereo_export::input_name(l), s, d))
        .collect();
    arrays.push(NamedArray::f32(TARGET_NAME, &b.target_shape, &b.target));
    // The features family: each sample's crops and taps (`warp.K.L.V.*`; none for a view
    // its sweep never sees), from which the graph computes and warps the source features.
    for (k, tile) in b.warps.iter().flatten().enumerate() {
        for (l, views) in tile.levels.iter().enumerate() {
            for (v, vw) in views.iter().enumerate() {
                let Some(vw) = vw else { continue };
                let stem = format!("{WARP_PREFIX}{k}.{l}.{v}");
                let (c, h, w) = vw.input_shape;
                arrays.push(NamedArray::f32(
                    &format!("{stem}.crop"),
                    &[c, h, w],
                    &vw.input,
                ));
                let (idx, wts) = vw.op.taps();
                let n = idx.len() / 4;
                arrays.push(NamedArray::i64(&format!("{stem}.index"), &[n, 4], &idx));
                arrays.push(NamedArray::f32(&format!("{stem}.weight"), &[n, 4], &wts));
            }
        }
    }
    arrays
}

/// Prefix of the features family's per-sample warp tensors in a shard.
const WARP_PREFIX: &str = "warp.";
