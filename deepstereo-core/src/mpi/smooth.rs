//! An MPI's selection smoothed across its image: a prior that depth varies smoothly.
//!
//! The network picks each pixel's planes on its own; where its choice wavers from pixel
//! to pixel, the MPI's planes hold a speckle of depths that a moved camera shows as
//! misplaced detail. Averaging every plane's share of the composite over a box of
//! texels gives neighbouring pixels one depth profile (measured in docs/results.md,
//! "MPIs").

use super::{alphas, Mpi};
use crate::error::Result;

impl Mpi {
    /// This MPI with each texel's selection (its planes' shares of the composite,
    /// `s_z = a_z prod_{k < z} (1 - a_k)`, near to far) replaced by its mean over the
    /// `(2 radius + 1)^2` box of texels around it (clipped to the image), on the planes
    /// the texel selects at all (a pruned bake's empty planes stay empty), and made
    /// alphas again ([`alphas`]); colours stay. Radius 0 gives the MPI unchanged. The
    /// composite at the reference changes: bakes restore it with
    /// [`Mpi::with_composite`].
    pub fn with_smoothed_selection(&self, radius: usize) -> Result<Self> {
        if radius == 0 {
            return Ok(self.clone());
        }
        let (w, h, d) = (self.width(), self.height(), self.planes.len());
        let own = self.shares();
        let mean = box_mean_planes(&own, d, (w, h), radius);
        let n = w * h;
        self.with_selection(|p, s| {
            for (z, v) in s.iter_mut().enumerate() {
                *v = if own[z * n + p] > 0.0 {
                    mean[z * n + p] as f32
                } else {
                    0.0
                };
            }
            true
        })
    }

    /// This MPI with each texel `p`'s alphas made from the selection `new(p, s)` writes
    /// into `s` (`[D]`, near to far; [`alphas`]), where `new` returns true; colours and
    /// the other texels stay.
    pub(super) fn with_selection(
        &self,
        mut new: impl FnMut(usize, &mut [f32]) -> bool,
    ) -> Result<Self> {
        let mut planes = self.planes.clone();
        let mut s = vec![0f32; planes.len()];
        for p in 0..self.width() * self.height() {
            if !new(p, &mut s) {
                continue;
            }
            for (z, a) in alphas(&s).into_iter().enumerate() {
                planes[z][p * 4 + 3] = a;
            }
        }
        let mut out = Self::new(self.camera, self.inv_depths.clone(), planes)?;
        out.margin = self.margin;
        Ok(out)
    }

    /// Per plane (near to far) and texel, `[D, H, W]`: its share of the composite at the
    /// reference, `a_z prod_{k < z} (1 - a_k)`.
    pub(super) fn shares(&self) -> Vec<f64> {
        let n = self.width() * self.height();
        let mut out = vec![0f64; self.planes.len() * n];
        for p in 0..n {
            let mut t = 1f64;
            for (z, plane) in self.planes.iter().enumerate() {
                let a = plane[p * 4 + 3] as f64;
                out[z * n + p] = a * t;
                t *= 1.0 - a;
            }
        }
        out
    }
}

/// Each of `d` planes `[H, W]` (`x` `[D, H, W]`) averaged over the `(2 r + 1)^2` box
/// around every texel, clipped to the image (a border texel averages fewer), by running
/// sums along rows, then along columns.
pub fn box_mean_planes(x: &[f64], d: usize, (w, h): (usize, usize), r: usize) -> Vec<f64> {
    let n = w * h;
    let mut out = vec![0f64; d * n];
    let mut rows = vec![0f64; n];
    for z in 0..d {
        let plane = &x[z * n..(z + 1) * n];
        for y in 0..h {
            box_mean_line(
                &plane[y * w..(y + 1) * w],
                1,
                r,
                &mut rows[y * w..(y + 1) * w],
                1,
            );
        }
        let dst = &mut out[z * n..(z + 1) * n];
        for col in 0..w {
            box_mean_line(&rows[col..], w, r, &mut dst[col..], w);
        }
    }
    out
}

/// The mean of `src`'s elements `[i - r, i + r]` (clipped to its length) for every `i`,
/// written to `dst`; `src` and `dst` read every `stride`-th element (a row or a column).
fn box_mean_line(src: &[f64], stride: usize, r: usize, dst: &mut [f64], dst_stride: usize) {
    let len = src.len().div_ceil(stride);
    let mut prefix = Vec::with_capacity(len + 1);
    prefix.push(0f64);
    let mut acc = 0f64;
    for i in 0..len {
        acc += src[i * stride];
        prefix.push(acc);
    }
    for i in 0..len {
        let (a, b) = (i.saturating_sub(r), (i + r + 1).min(len));
        dst[i * dst_stride] = (prefix[b] - prefix[a]) / (b - a) as f64;
    }
}
