//! Rolling-shutter rigs: every view's camera keeps moving along the rig's path while its
//! rows are read out.
//!
//! View `i`'s readout starts at its rig pose `P_i` (`t = 0`, top edge of the image) and
//! ends (`t = 1`, bottom edge) at the pose a share `S` of the way to the next view's,
//! `P_i -> P_{i+1}` (centre linear, rotation spherical, as [`Motion`] interpolates); the
//! last view continues the motion from the one before it. The time of pixel `(u, v)` is
//! `t = v / H` (instant-ngp `rolling_shutter = [0, 0, 1, 0]`).

use crate::camera::rolling::Motion;
use crate::camera::{Camera, RollingShutter, WorldToCamera};
use crate::error::{Error, Result};
use glam::DVec2;

/// Gives the cameras (in path order) rolling shutters whose readout covers the share
/// `share` of the motion between neighbouring views (nothing changes for `share = 0`).
/// `check` validates each view's end-of-readout camera.
pub(crate) fn apply(
    cameras: &mut [Camera],
    share: f64,
    check: impl Fn(&Camera) -> std::result::Result<(), String>,
) -> Result<()> {
    if share == 0.0 || cameras.len() < 2 {
        return Ok(());
    }
    let starts: Vec<WorldToCamera> = cameras.iter().map(|c| c.pose).collect();
    let n = starts.len();
    for (i, cam) in cameras.iter_mut().enumerate() {
        let end = if i + 1 < n {
            Motion::new(&starts[i], &starts[i + 1]).pose(share)
        } else {
            Motion::new(&starts[i - 1], &starts[i]).pose(1.0 + share)
        };
        let k = cam.intrinsics;
        let per_pixel = DVec2::new(0.0, 1.0 / k.height as f64);
        let rs = RollingShutter::new_checked(starts[i], end, 0.0, per_pixel)
            .map_err(|m| Error::Invalid(format!("synth: view {i}: {m}")))?;
        check(&Camera::global(k, end)).map_err(|m| {
            Error::Invalid(format!("synth: view {i} at the end of its readout: {m}"))
        })?;
        *cam = Camera::rolling(k, rs);
    }
    Ok(())
}
