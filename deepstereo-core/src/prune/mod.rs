//! Leaving out the work a given scene does not need (`--prune auto`).
//!
//! DeepStereo's cost grows with planes x views x pixels. For one target, most planes hold
//! no surface, some candidate sources do not see the target, and some tiles are seen by
//! no source. With pruning on, the renderer:
//!
//! - **Depth range** ([`plane_range_from_points`], [`plane_range_from_bounds`]): when the
//!   scene has sparse points, considers only the planes between the nearest and farthest
//!   points the target sees; else, when the views have their own depth bounds (LLFF), only
//!   the planes within the sources' bounds.
//!   The plane grid (uniform in inverse depth between the scene's near and far) is not
//!   changed, so every plane the network runs on is a plane of the unpruned render.
//! - **Plane spacing** ([`max_plane_step`], [`thin_planes`]): when the requested planes
//!   are closer than a pixel of disparity apart in every source (measured on a grid of
//!   target pixels), fewer planes spread evenly over the grid are run: 96 planes over a
//!   scene whose disparity range is 19 pixels (0.2 px apart) need 20 of them. Beyond a
//!   pixel, planes are thinned down to the model's own count while the step stays within
//!   [`PruneOptions::max_step`] pixels, and to three quarters of it ([`thin_floor`])
//!   while it stays within [`FINE_STEP`] (2 pixels): with the rest of pruning, the
//!   default model renders such thinned planes above the unpruned render's PSNR at 32,
//!   64 and 96 planes on every scene measured (`docs/performance.md`, `prune_eval.sh`),
//!   at a fraction of the cost.
//!   The coarse pass below runs on every second plane of the range or sparser, at most
//!   the model's plane count ([`guide_planes`]; each plane standing for its neighbours).
//! - **Planes per block** ([`Pruner::plan`]): a coarse pass says which planes each block
//!   of a tile needs. By default ([`CoarsePass::Network`], [`network_guide`]) it is the
//!   network itself, run at `1 / 2^guide_level` resolution (1/16 of the pixels) on every
//!   plane of the depth range: each block keeps, for every coarse pixel under it (and
//!   one around it), the most probable planes holding [`PruneOptions::keep`] of its
//!   selection (or, once they hold [`COLOUR_MIN_MASS`] of it, as few as leave its
//!   colour within [`PruneOptions::error`] of the colour of all planes, where the
//!   backend gives per-plane colours), and [`PruneOptions::margin`] planes on each side.
//!   [`CoarsePass::Photo`] instead scores planes by photo-consistency: every second
//!   pixel of the tile at pyramid level 1, on every plane of the range, scored by the
//!   smallest mean squared colour difference between two sources over a window of
//!   samples (two sources agreeing is enough, so occlusion in the others does not hide a
//!   surface); each sample whose score tells depths apart keeps its best plane
//!   ([`PruneOptions::tolerance`] widens that), and its best plane without the window when
//!   that one stands out ([`PruneOptions::standout`]: thin structures).
//!   Either way the network runs once per block on the kept planes, in order (the
//!   selection tower accepts any list of planes), and a tile whose parts need different
//!   planes is split into quadrants (down to [`PruneOptions::min_block`] pixels) when that
//!   costs less, counting a fixed cost per network call. Only the kept planes are warped;
//!   the selection is 0 elsewhere, so the depth and confidence maps keep their meaning.
//!   A contiguous band of planes per tile does not work: a 64-pixel tile of a procedural
//!   scene holds on average surfaces spanning 81% of the depth range (measured from the
//!   true depths), while the planes those surfaces are on are 26% of it.
//! - **Views** ([`rank_views`]): candidate sources are ranked by how much of the target
//!   frustum they see, discounted by their distance; views that see too little are left
//!   out, and when fewer useful views than the model takes exist, the nearest fill in.
//! - **Pixels**: a tile whose input footprint no source covers at any plane skips the
//!   network and takes the network's response to empty input (computed once per render:
//!   exactly what the network gives there); a tile whose sampled source colours are all
//!   equal (within [`PruneOptions::flat`]) takes their mean colour, with the selection
//!   spread uniformly over the depth range.
//!
//! Neither coarse pass finds every surface: textureless, repetitive and occluded parts
//! fool photo-consistency, and the coarse network blurs thin structures. A pixel whose
//! true plane pruning leaves out gets the network's best choice among the kept planes.
//! The tests bound how often that happens where the depth is knowable: never for the
//! textured pixels whose depth the classical plane sweep recovers away from occlusion
//! edges, and for at most 0.5% of them in all.
//!
//! With [`PruneMode::Off`] nothing of this runs and the renderer is the unpruned one.
//!
//! Rolling-shutter cameras ([`crate::camera::rolling`]): the depth range, plane spacing,
//! view ranking and the photo-consistency coarse pass use each camera's mid-readout
//! `pose` (the readout's motion is an error of a few pixels there, well within the
//! margins those estimates keep); the sweeps the network itself runs on project every
//! pixel through the rolling shutters exactly.

mod guide;
mod plan;
mod range;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_calibrate;
#[cfg(test)]
mod tests_guide;
mod views;

pub use guide::{guide_planes, needed_prefix, network_guide, Guide, COLOUR_MIN_MASS};
pub use plan::{Block, Pruner, TilePlan};
pub use range::{
    max_plane_step, plane_range_from_bounds, plane_range_from_points, span_planes, thin_floor,
    thin_planes, BOUNDS_MARGIN, FINE_STEP, MIN_CLOUD_POINTS, POINT_MARGIN, POINT_QUANTILES,
    SUBPIXEL_STEP,
};
pub use views::{rank_views, view_coverage, ViewRank, MIN_VIEW_COVERAGE};

use crate::config::Config;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Whether the renderer prunes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PruneMode {
    /// Every plane, the nearest views, every tile: the unpruned renderer.
    #[default]
    Off,
    /// Leave out planes, views and tiles the scene does not need.
    Auto,
}

impl PruneMode {
    pub fn name(self) -> &'static str {
        match self {
            PruneMode::Off => "off",
            PruneMode::Auto => "auto",
        }
    }
}

impl std::fmt::Display for PruneMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for PruneMode {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "off" => Ok(PruneMode::Off),
            "auto" => Ok(PruneMode::Auto),
            o => Err(Error::Invalid(format!(
                "unknown prune mode '{o}' (expected off or auto)"
            ))),
        }
    }
}

/// Default of [`PruneOptions::mass`].
pub const DEFAULT_MASS: f32 = 1.0;
/// Default of [`PruneOptions::margin`].
pub const DEFAULT_MARGIN: usize = 2;
/// Default of [`PruneOptions::tolerance`].
pub const DEFAULT_TOLERANCE: f32 = 0.0;
/// Default of [`PruneOptions::stride`].
pub const DEFAULT_STRIDE: usize = 2;
/// Default of [`PruneOptions::window`].
pub const DEFAULT_WINDOW: usize = 2;
/// Default of [`PruneOptions::standout`].
pub const DEFAULT_STANDOUT: f32 = 0.1;
/// Default of [`PruneOptions::flat`].
pub const DEFAULT_FLAT: f32 = 1.0 / 255.0;
/// Default of [`PruneOptions::error`].
pub const DEFAULT_ERROR: f32 = 0.0;
/// Default of [`PruneOptions::keep`].
pub const DEFAULT_KEEP: f32 = 0.95;
/// Default of [`PruneOptions::max_step`]: the embedded model gains from planes closer
/// than its own 32 (juicebox lost 0.2-0.3 dB at 64 and 96 planes thinned with a step of
/// 8), and a step of 4 kept so many that a procedural scene at 64 planes ran only 1.5x
/// faster than unpruned (`docs/performance.md`).
pub const DEFAULT_MAX_STEP: f64 = 5.0;
/// Default of [`PruneOptions::guide_level`].
pub const DEFAULT_GUIDE_LEVEL: usize = 2;

/// Which coarse pass chooses the planes of each block.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CoarsePass {
    /// The network itself at `1 / 2^guide_level` resolution on every plane of the depth
    /// range: each block keeps the planes that hold [`PruneOptions::keep`] of the
    /// selection of the coarse pixels under it.
    #[default]
    Network,
    /// Photo-consistency of the sources at pyramid level [`PruneOptions::level`].
    Photo,
}

impl std::str::FromStr for CoarsePass {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "network" => Ok(CoarsePass::Network),
            "photo" => Ok(CoarsePass::Photo),
            o => Err(Error::Invalid(format!(
                "unknown coarse pass '{o}' (expected network or photo)"
            ))),
        }
    }
}

/// Default of [`PruneOptions::min_block`].
pub const DEFAULT_MIN_BLOCK: usize = 16;
/// Default of [`PruneOptions::contrast`].
pub const DEFAULT_CONTRAST: f32 = 1e-4;

/// How much to prune (see the module docs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PruneOptions {
    pub mode: PruneMode,
    /// Which coarse pass picks the planes.
    pub coarse: CoarsePass,
    /// [`CoarsePass::Network`]: per coarse pixel, the fraction of its selection
    /// probability the kept planes must hold (1 keeps every plane).
    pub keep: f32,
    /// [`CoarsePass::Network`] with a backend that returns per-plane colours: a coarse
    /// pixel needs no more planes once those kept hold [`COLOUR_MIN_MASS`] of its
    /// selection and leaving out the rest moves its colour by at most this (0-1, every
    /// channel; 0: `keep` alone decides).
    pub error: f32,
    /// [`CoarsePass::Network`]: pyramid level of the coarse render (2: a quarter of the
    /// resolution, 1/16 of the pixels).
    pub guide_level: usize,
    /// Largest disparity step, in source pixels, between the planes kept: requested
    /// planes closer than [`SUBPIXEL_STEP`] in every source are thinned (spread evenly),
    /// and beyond that down to the model's own plane count while the step stays within
    /// this (and to three quarters of it within [`FINE_STEP`]; 0: never thin; see
    /// [`thin_planes`]).
    pub max_step: f64,
    /// Fraction of the coarse samples' support (each informative sample spreads one unit
    /// over its plausible planes) the kept planes must hold, most supported planes first
    /// (1: every plane some sample finds plausible; lower is faster and drops thin
    /// structures first).
    pub mass: f32,
    /// Planes added on each side of every kept plane. The selection tower's convolutions
    /// along depth look [`depth_reach`] planes away (3 for the presets), so only a margin
    /// that large makes the kept planes' logits exactly the unpruned ones; in measurement
    /// a margin of 1 loses nothing measurable at a much lower cost.
    pub margin: usize,
    /// A coarse sample's plausible planes: those whose cost lies within `tolerance` x its
    /// cost range of its least cost (0: only its best plane).
    pub tolerance: f32,
    /// Spacing of the coarse samples in level-0 pixels.
    pub stride: usize,
    /// Pyramid level the coarse pass samples (clamped to the model's levels).
    pub level: usize,
    /// A sample whose cost range across planes is below this (mean squared colour
    /// difference) says nothing about depth (textureless) and keeps no plane.
    pub contrast: f32,
    /// A tile is flat when every sampled source colour lies within this of the mean.
    pub flat: f32,
    /// Radius, in coarse samples, of the window costs are averaged over.
    pub window: usize,
    /// A sample also keeps its own best plane, without the window, when that plane's cost
    /// is at most `standout` x its median cost: thin structures the window averages away.
    pub standout: f32,
    /// Smallest block a tile is split into when its parts need different planes.
    pub min_block: usize,
}

impl Default for PruneOptions {
    fn default() -> Self {
        Self {
            mode: PruneMode::Off,
            coarse: CoarsePass::Network,
            keep: DEFAULT_KEEP,
            error: DEFAULT_ERROR,
            guide_level: DEFAULT_GUIDE_LEVEL,
            max_step: DEFAULT_MAX_STEP,
            mass: DEFAULT_MASS,
            margin: DEFAULT_MARGIN,
            tolerance: DEFAULT_TOLERANCE,
            stride: DEFAULT_STRIDE,
            level: 1,
            contrast: DEFAULT_CONTRAST,
            flat: DEFAULT_FLAT,
            min_block: DEFAULT_MIN_BLOCK,
            window: DEFAULT_WINDOW,
            standout: DEFAULT_STANDOUT,
        }
    }
}

impl PruneOptions {
    /// Pruning off.
    pub fn off() -> Self {
        Self::default()
    }

    /// Pruning on, default thresholds.
    pub fn auto() -> Self {
        Self {
            mode: PruneMode::Auto,
            ..Self::default()
        }
    }

    pub fn is_on(&self) -> bool {
        self.mode == PruneMode::Auto
    }

    /// Checks the thresholds, with a message naming the bad one.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::Invalid(m));
        if !(self.mass > 0.0 && self.mass <= 1.0) {
            return bad(format!("--prune-mass must be in (0, 1], got {}", self.mass));
        }
        if !(self.keep > 0.0 && self.keep <= 1.0) {
            return bad(format!("--prune-keep must be in (0, 1], got {}", self.keep));
        }
        if !(self.error >= 0.0 && self.error.is_finite()) {
            return bad(format!(
                "--prune-error must be a finite number >= 0, got {}",
                self.error
            ));
        }
        if !(self.max_step >= 0.0 && self.max_step.is_finite()) {
            return bad(format!(
                "--prune-max-step must be a finite number >= 0, got {}",
                self.max_step
            ));
        }
        if self.guide_level == 0 {
            return bad("--prune-guide-level must be at least 1".into());
        }
        if !(self.tolerance >= 0.0 && self.tolerance <= 1.0) {
            return bad(format!(
                "--prune-tolerance must be in [0, 1], got {}",
                self.tolerance
            ));
        }
        if self.stride == 0 {
            return bad("--prune-stride must be at least 1".into());
        }
        if !(self.contrast >= 0.0 && self.flat >= 0.0) {
            return bad("prune thresholds must be non-negative".into());
        }
        Ok(())
    }
}

/// How far (in planes) the selection tower's convolutions along depth look on each side.
pub fn depth_reach(cfg: &Config) -> usize {
    cfg.depth_convs.iter().map(|c| c.kernel / 2).sum()
}

/// What pruning did in one render.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct PruneStats {
    pub tiles: usize,
    /// Tiles no source covers (network skipped).
    pub uncovered: usize,
    /// Tiles whose sources are constant there (network skipped).
    pub flat: usize,
    /// Planes the network ran on times the pixels of the blocks it ran them on.
    pub planes_run: usize,
    /// The same for the unpruned render (planes times the pixels of every tile).
    pub planes_total: usize,
    /// The planes the depth range kept (`first..=last`), when the scene had points.
    pub depth_range: Option<(usize, usize)>,
    /// When the plane grid was thinned (see [`PruneOptions::max_step`]): the planes
    /// requested and the planes kept.
    pub thinned: Option<(usize, usize)>,
    /// Seconds in the coarse pass.
    pub coarse_seconds: f64,
    /// Seconds building the network's inputs (warping the kept planes).
    pub warp_seconds: f64,
    /// Seconds in the network.
    pub network_seconds: f64,
    /// Network calls (blocks run).
    pub calls: usize,
}

impl PruneStats {
    /// Fraction of the unpruned render's plane-pixels the network ran on.
    pub fn planes_fraction(&self) -> f64 {
        if self.planes_total == 0 {
            1.0
        } else {
            self.planes_run as f64 / self.planes_total as f64
        }
    }

    /// A line for people.
    pub fn summary(&self) -> String {
        let mut range = match self.depth_range {
            Some((a, b)) => format!(", depth range planes {a}..={b}"),
            None => String::new(),
        };
        if let Some((of, kept)) = self.thinned {
            range = format!(", {kept} of {of} planes by disparity step{range}");
        }
        format!(
            "prune: network on {:.0}% of the planes x pixels ({} tiles, {} uncovered, {} flat{range}; {} network calls; seconds: coarse pass {:.2}, warping {:.2}, network {:.2})",
            100.0 * self.planes_fraction(),
            self.tiles,
            self.uncovered,
            self.flat,
            self.calls,
            self.coarse_seconds,
            self.warp_seconds,
            self.network_seconds
        )
    }
}
