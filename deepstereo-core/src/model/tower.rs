//! The 2D part of a tower: per-level convolutions, their crops upsampled to the tile, and
//! the merge convolutions.

use crate::config::TowerConfig;
use crate::conv::Conv2d;
use crate::fused::{upsample_cat, upsample_crop};
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

/// The 2D part of a tower (see [`TowerConfig`]).
#[derive(Debug, Clone)]
pub struct Tower {
    cfg: TowerConfig,
    levels: Vec<Vec<Conv2d>>,
    merge: Vec<Conv2d>,
}

impl Tower {
    pub(super) fn new(cfg: &TowerConfig, in_channels: usize, vb: VarBuilder) -> Result<Self> {
        let mut levels = Vec::with_capacity(cfg.levels);
        for l in 0..cfg.levels {
            let vbl = vb.pp("levels").pp(l);
            let mut ch = in_channels;
            let mut convs = Vec::new();
            for (i, c) in cfg.level_convs.iter().enumerate() {
                convs.push(Conv2d::new(
                    ch,
                    c.channels,
                    (c.kernel, c.kernel),
                    vbl.pp(i),
                )?);
                ch = c.channels;
            }
            levels.push(convs);
        }
        let mut ch = cfg.level_channels(in_channels) * cfg.levels;
        let mut merge = Vec::new();
        for (i, c) in cfg.merge_convs.iter().enumerate() {
            merge.push(Conv2d::new(
                ch,
                c.channels,
                (c.kernel, c.kernel),
                vb.pp("merge").pp(i),
            )?);
            ch = c.channels;
        }
        Ok(Self {
            cfg: cfg.clone(),
            levels,
            merge,
        })
    }

    /// The convolutions in order when the tower is one level of 1x1 convolutions (its
    /// merge then needs no crop or concatenation).
    pub(super) fn pointwise(&self) -> Option<Vec<&Conv2d>> {
        let convs: Vec<&Conv2d> = self.levels.first()?.iter().chain(&self.merge).collect();
        let ones = convs.iter().all(|c| c.weight().dims()[2..] == [1, 1]);
        (self.levels.len() == 1 && ones && !convs.is_empty()).then_some(convs)
    }

    /// `inputs[l]`: `[N, C_in, H_l, W_l]` (N = B*D planes folded into the batch), each
    /// already cropped to this tower's footprint. Returns `[N, C, th, tw]`. With `fuse`
    /// (rendering: no gradients), the levels' crops are written straight into their
    /// concatenation ([`upsample_cat`]).
    pub(super) fn forward(
        &self,
        inputs: &[Tensor],
        th: usize,
        tw: usize,
        fuse: bool,
    ) -> Result<Tensor> {
        let rf = self.cfg.merge_reduction();
        let mut levels = Vec::with_capacity(self.levels.len());
        for (l, convs) in self.levels.iter().enumerate() {
            let mut x = inputs[l].clone();
            for conv in convs {
                x = conv.forward_relu(&x)?;
            }
            levels.push(x); // [N, C, H_l, W_l]
        }
        let crops: Vec<(&Tensor, usize, usize)> = (levels.iter().enumerate())
            .map(|(l, x)| (x, 1 << l, self.cfg.upsample_crop(l)))
            .collect();
        let merged = match fuse && levels.len() > 1 {
            true => upsample_cat(&crops, th + rf, tw + rf)?,
            false => None,
        };
        let mut x = match merged {
            Some(x) => x,
            None => self.merge_input(&crops, th + rf, tw + rf)?,
        }; // [N, sum C, th+rf, tw+rf]
        for conv in &self.merge {
            x = conv.forward_relu(&x)?;
        }
        Ok(x) // [N, C, th, tw]
    }

    /// The levels' features `(x_l [N, C, H_l, W_l], 2^l, offset)` upsampled, cropped to
    /// `h x w` and concatenated, as differentiable ops: `[N, sum C, h, w]`.
    pub(super) fn merge_input(
        &self,
        crops: &[(&Tensor, usize, usize)],
        h: usize,
        w: usize,
    ) -> Result<Tensor> {
        let feats = crops
            .iter()
            .map(|&(x, s, off)| match s {
                1 => x.narrow(2, off, h)?.narrow(3, off, w),
                _ => upsample_crop(x, s, off, h, w),
            }) // [N, C, h, w]
            .collect::<Result<Vec<_>>>()?;
        Tensor::cat(&feats, 1) // [N, sum C, h, w]
    }
}
