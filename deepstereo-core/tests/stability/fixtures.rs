//! Fixtures of the network and optimizer cases: a small config with every part of the
//! model and seeded input levels. Shared by this crate's stability suite and
//! deepstereo-train's optimizer cases (`deepstereo-train/tests/stability_optim.rs`,
//! which includes this file by path).

use anyhow::Result;
use candle_core::{Device, Tensor};
use deepstereo_core::config::{Config, Conv, TowerConfig};

/// A small config with every part of the model (2 levels, merge, depth convs, skip).
pub fn small() -> Config {
    let c = |k, ch| Conv {
        kernel: k,
        channels: ch,
    };
    Config {
        name: "small".into(),
        views: 2,
        planes: 5,
        levels: 2,
        tile: 4,
        select: TowerConfig {
            levels: 2,
            level_convs: vec![c(3, 4)],
            merge_convs: vec![c(3, 4)],
        },
        depth_convs: vec![c(3, 3), c(3, 1)],
        colour: TowerConfig {
            levels: 1,
            level_convs: vec![c(1, 3)],
            merge_convs: vec![c(3, 3)],
        },
        colour_skip: true,
        render_planes: None,
        pool: None,
    }
}

/// Uniform values in [0, 1) from a seed (LCG).
pub fn rand01(seed: u64) -> impl FnMut() -> f32 {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// Input levels `[B, D, 4V, H_l, W_l]` for a tile of `th`, each value from
/// `fill(is_alpha, uniform)`.
pub fn inputs(
    cfg: &Config,
    b: usize,
    d: usize,
    th: usize,
    seed: u64,
    fill: impl Fn(bool, f32) -> f32,
) -> Result<Vec<Tensor>> {
    let mut u = rand01(seed);
    (0..cfg.levels)
        .map(|l| {
            let s = cfg.input_size(l, th);
            let c = cfg.in_channels();
            let data: Vec<f32> = (0..b * d * c * s * s)
                .map(|i| fill((i / (s * s)) % c % 4 == 3, u()))
                .collect();
            Ok(Tensor::from_vec(data, (b, d, c, s, s), &Device::Cpu)?)
        })
        .collect()
}
