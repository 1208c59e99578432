//! The plane sweep's sampling positions: for every plane, source and target pixel, the
//! source pixel coordinate the sweep samples (the same f64 projection as
//! [`super::sweep_into`], rolling shutters included), so that anything defined on a
//! source's pixel grid (the `features` family's feature maps, [`crate::features`]) is
//! warped into the sweep exactly where its colours are.
//!
//! Layout over a region of `h x w` target pixels: `[D, V, 2, h, w]` f64, `(u, v)` in the
//! source's pixel coordinates (pixel `(i, j)` has its centre at `(i + 0.5, j + 0.5)`), NaN
//! where the plane point has no projection (RGBA = 0 there).

use super::rolling::{project_rolling, target_world_rays};
use super::{project_slice, target_rays, Region};
use crate::camera::{Camera, WorldToCamera};
use crate::geometry::plane_homography;
use rayon::prelude::*;

/// Fills `out` (`[D, V, 2, h, w]`, length `D * V * 2 * h * w`) with the source pixel
/// coordinates of the sweep of `sources` seen from `target` over `region` at
/// `inv_depths` (NaN: no projection).
pub fn sweep_coords_into(
    target: &Camera,
    region: Region,
    sources: &[&Camera],
    inv_depths: &[f64],
    out: &mut [f64],
) {
    let hw = region.len();
    let v = sources.len();
    debug_assert_eq!(out.len(), inv_depths.len() * v * 2 * hw);
    if hw == 0 || v == 0 {
        return;
    }
    let target_moves = target.moving_shutter().is_some();
    let rays = target_rays(&target.intrinsics, region);
    let world = (target_moves || sources.iter().any(|s| s.moving_shutter().is_some()))
        .then(|| target_world_rays(target, region));
    let rels: Vec<WorldToCamera> = sources
        .iter()
        .map(|s| target.pose.relative_to(&s.pose))
        .collect();
    out.par_chunks_mut(2 * hw)
        .enumerate()
        .for_each(|(slice, chunk)| {
            let (d, k) = (slice / v, slice % v);
            let (us, vs) = chunk.split_at_mut(hw);
            let mut put = |i: usize, uv: Option<glam::DVec2>| {
                let uv = uv.unwrap_or(glam::DVec2::NAN);
                us[i] = uv.x;
                vs[i] = uv.y;
            };
            match &world {
                Some(world) if target_moves || sources[k].moving_shutter().is_some() => {
                    project_rolling(world, inv_depths[d], sources[k], put)
                }
                _ => {
                    let h = plane_homography(&rels[k], inv_depths[d]);
                    project_slice(&h, &rays, &sources[k].intrinsics, &mut put)
                }
            }
        });
}

/// Allocating wrapper of [`sweep_coords_into`].
pub fn sweep_coords(
    target: &Camera,
    region: Region,
    sources: &[&Camera],
    inv_depths: &[f64],
) -> Vec<f64> {
    let mut out = vec![0.0; inv_depths.len() * sources.len() * 2 * region.len()];
    sweep_coords_into(target, region, sources, inv_depths, &mut out);
    out
}
