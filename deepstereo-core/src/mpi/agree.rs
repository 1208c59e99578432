//! An MPI's selection reweighed by how well the reference photograph agrees with the
//! sources at each plane: plane-sweep stereo with the photograph.
//!
//! A bake's depths come from the network run on the other views (the photograph among
//! the sources would agree with itself at every depth). The photograph still says which
//! depths are right: at plane `z` of texel `p`, the sources warped through that plane
//! show the photograph's colour where the surface lies on it. Each texel's selection
//! (its planes' shares of the composite) is multiplied by
//!
//! `f_z = exp(-e_z / tau)`, `e_z` the mean of the closer half of `e_{z,v} = mean_rgb
//! |I(p) - c_v(p)|` over the sources `v` that see the point,
//!
//! with `I` the photograph warped to the reference through the plane (the MPI's
//! reference camera is a pinhole; the photograph's own camera may have lens distortion or
//! a rolling shutter) and `c_v` source `v` warped there (the sweep's colours divided by
//! its coverage). The closer half, not all: a source that sees another face of the
//! object or an occluder there disagrees at every depth, and the best-matching subset of
//! views is the classical remedy for occlusions in multi-view matching (Kang, Szeliski and
//! Chai, CVPR 2001). A source counts where its coverage is at least [`MIN_COVERAGE`];
//! where the photograph or no source sees the point, and in the margin, `f_z = 1`.
//! Measured in docs/results.md, "MPIs".

use super::Mpi;
use crate::error::{Error, Result};
use crate::sweep::{sweep_into, try_zeroed, Region, Source, CHANNELS};
use rayon::prelude::*;

/// Coverage below which a view does not see a plane point (the photograph: its factor
/// stays 1; a source: it is left out of the errors).
pub const MIN_COVERAGE: f64 = 0.5;

impl Mpi {
    /// This MPI with every texel of the view it was baked for (its margin left out)
    /// reweighed by the agreement of `photo` (the reference view and its photograph)
    /// with `sources` at each plane, `tau` the colour scale (RGB in [0, 1]); alphas
    /// follow from the new selection ([`super::alphas`]), colours stay. The composite at the
    /// reference changes: bakes restore it with [`Mpi::with_composite`].
    pub fn with_photo_agreement(
        &self,
        photo: Source<'_>,
        sources: &[Source<'_>],
        tau: f64,
    ) -> Result<Self> {
        if !(tau.is_finite() && tau > 0.0) {
            return Err(Error::Invalid(format!(
                "the agreement's colour scale must be positive and finite, not {tau}"
            )));
        }
        let factors = self.agreement(photo, sources, tau)?;
        self.with_reweighed_selection(&factors)
    }

    /// `f_z` per plane and texel of the whole image, `[D, H, W]` (1 in the margin).
    pub(super) fn agreement(
        &self,
        photo: Source<'_>,
        sources: &[Source<'_>],
        tau: f64,
    ) -> Result<Vec<f32>> {
        let (w, h, d) = (self.width(), self.height(), self.inv_depths.len());
        let m = self.margin as usize;
        let region = Region {
            x0: m as i64,
            y0: m as i64,
            width: w.saturating_sub(2 * m),
            height: h.saturating_sub(2 * m),
        };
        let mut out = try_zeroed(&[d, w, h], "the agreement of the photograph")?;
        out.fill(1.0);
        let n = region.len();
        if n == 0 || sources.is_empty() {
            return Ok(out);
        }
        let views: Vec<Source<'_>> = std::iter::once(photo)
            .chain(sources.iter().copied())
            .collect();
        let mut slice = try_zeroed(
            &[views.len(), CHANNELS, n],
            "a plane of the agreement's sweep",
        )?;
        for (z, &rho) in self.inv_depths.iter().enumerate() {
            sweep_into(&self.camera, region, &views, &[rho], &mut slice);
            let plane = &mut out[z * w * h..(z + 1) * w * h];
            let rows = plane.par_chunks_mut(w).skip(m).take(region.height);
            rows.enumerate().for_each(|(y, row)| {
                let mut errors = Vec::with_capacity(views.len());
                for (x, f) in row[m..m + region.width].iter_mut().enumerate() {
                    let p = y * region.width + x;
                    *f = factor(&slice, views.len(), n, p, tau, &mut errors);
                }
            });
        }
        Ok(out)
    }

    /// This MPI with each texel's selection `s_z` made `s_z f_z` (the alphas of
    /// [`super::alphas`] normalize it: the farthest plane selected is opaque); a texel whose
    /// reweighed selection vanishes keeps its own.
    pub(super) fn with_reweighed_selection(&self, factors: &[f32]) -> Result<Self> {
        let (own, n) = (self.shares(), self.width() * self.height());
        self.with_selection(|p, s| {
            for (z, v) in s.iter_mut().enumerate() {
                *v = (own[z * n + p] * factors[z * n + p] as f64) as f32;
            }
            s.iter().any(|&v| v > 0.0)
        })
    }
}

/// `exp(-e / tau)` at pixel `p` of one plane's sweep `[V, 4, n]`, view 0 the photograph
/// and the others the sources, `e` the mean of the closer half of the sources' errors
/// (those that see the point); 1 where the photograph or no source sees it.
fn factor(slice: &[f32], views: usize, n: usize, p: usize, tau: f64, errors: &mut Vec<f64>) -> f32 {
    let at = |v: usize, ch: usize| slice[(v * CHANNELS + ch) * n + p] as f64;
    let photo_alpha = at(0, 3);
    if photo_alpha < MIN_COVERAGE {
        return 1.0;
    }
    errors.clear();
    for v in (1..views).filter(|&v| at(v, 3) >= MIN_COVERAGE) {
        let (a, b) = (photo_alpha, at(v, 3));
        let e: f64 = (0..3).map(|ch| (at(0, ch) / a - at(v, ch) / b).abs()).sum();
        errors.push(e / 3.0);
    }
    if errors.is_empty() {
        return 1.0;
    }
    errors.sort_unstable_by(f64::total_cmp);
    let closer = &errors[..errors.len().div_ceil(2)];
    let e = closer.iter().sum::<f64>() / closer.len() as f64;
    (-e / tau).exp() as f32
}
