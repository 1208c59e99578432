//! Winograd minimal-filtering forward (f32, AVX2 and FMA) for the 3x3 and 5x5 layers with
//! output channels a multiple of [`CV`]: F(2x2, 5x5) and F(4x4, 3x3), both on 6x6 input
//! tiles (A = 6), so an output tile costs 36 products per input channel and output channel
//! instead of 100 (5x5) or 144 (3x3).
//!
//! With `U = G w G^T` (weights, once per call, in f64), `V = B^T d B` (each input tile `d`)
//! and `Y = A^T M A` for `M[pos][co] = sum_ci U[pos][co][ci] V[pos][ci]`, the 36 products
//! `M[pos]` are 36 small matrix products, run by `direct_cv.rs`'s tile kernel (16 output
//! channels x 6 tiles, one tap per input channel). The transforms (`algos.rs`) come from
//! Toom-Cook on the points 0, 1, -1, 1/2, -1/2 (5x5) or 0, 1, -1, 1/2, -2 (3x3) and
//! infinity; `python/winograd_transforms.py` derives them exactly and measures their f32
//! error on random tiles of 64 channels: 1.2e-7 (5x5) and 2.5e-7 (3x3) of the sum of the
//! products' magnitudes, against 1.0e-7 and 1.8e-7 for a direct f32 sum.
//!
//! Work units are runs of up to [`UNIT_TILES`] tile slots of one image (see [`Layout`]):
//! transform the unit's input tiles into `V[pos][ci][slot]` (`transforms.rs`), multiply
//! into `M[pos][co][slot]`, transform back with bias and ReLU into the output (tiles that
//! overhang the output's edge read zeros and drop the outputs past it). 24 slots keep a
//! unit's `V` and `M` in L2 (with 48, 1.1 MB at 64 -> 96 channels, the layer ran slower).

mod algos;
mod transforms;

use super::direct::LineAligned;
#[cfg(target_arch = "x86_64")]
use super::direct_cv::gemm_groups;
use super::direct_cv::{CV, NP};
use super::im2col::Geom;
use crate::cpu::{avx2_fma_available as available, SharedMut};
use algos::{Algo, F25, F43};
use rayon::prelude::*;
use transforms::{input_transform, output_transform};

/// Input tile side.
const A: usize = 6;
/// Products per tile (transformed positions).
const POS: usize = A * A;
/// Tiles per work unit (a multiple of [`NP`] and of [`LANES`]).
const UNIT_TILES: usize = 24;
/// Tiles the transforms handle at once (one 8-lane vector each).
const LANES: usize = 8;
/// Runs of units per thread (each allocates its scratch once).
const CHUNKS_PER_THREAD: usize = 4;
/// Fewest output channels for this path: the input transform's cost is per input
/// channel, the products' per output channel (with 16 outputs the direct kernel was
/// faster on the `paper` layers).
const MIN_COUT: usize = 32;
/// Least [`saving`] for this path (the transforms cost the rest): the `paper` layer with
/// 5x5 outputs of a 3x3 kernel (saving 1.04) ran 1.25x slower than the direct kernel,
/// a 5x5 kernel's 7x7 outputs (1.42) 1.6x faster.
const MIN_SAVING: f64 = 1.3;
/// Fewest input channels for this path (below it the transforms cost more than they save).
const MIN_CIN: usize = 8;

/// Whether [`forward`] can run this layer (f32 callers only; `plan.rs` chooses).
pub(crate) fn applies(g: &Geom) -> bool {
    available()
        && g.kh == g.kw
        && matches!(g.kh, 3 | 5)
        && g.cout.is_multiple_of(CV)
        && g.cout >= MIN_COUT
        && g.cin >= MIN_CIN
        && saving(g) >= MIN_SAVING
}

/// Products of the direct convolution over those of the Winograd one, counting the tile
/// slots that overhang the output or pad the layout: `R^2 Ho Wo / (36 slots)`.
fn saving(g: &Geom) -> f64 {
    let lay = if g.kh == 5 {
        Layout::new::<F25>(g)
    } else {
        Layout::new::<F43>(g)
    };
    (g.kh * g.kh * g.ho() * g.wo()) as f64 / (POS * lay.slots()) as f64
}

/// `y = act(conv(x, w) + b)`, as [`super::kernels::forward`]; call only when
/// [`applies`] holds.
pub(crate) fn forward(g: &Geom, x: &[f32], w: &[f32], b: &[f32], relu: bool) -> Vec<f32> {
    if g.kh == 5 {
        run::<F25>(g, x, w, b, relu)
    } else {
        run::<F43>(g, x, w, b, relu)
    }
}

/// `U[pos][panel][ci][CV]`: each `[R, R]` kernel as `G w G^T` (f64, then rounded),
/// channels in panels of [`CV`] as the tile kernel reads them.
fn transform_weights<T: Algo>(g: &Geom, w: &[f32]) -> LineAligned {
    let (cin, cout, r) = (g.cin, g.cout, T::R);
    let mut u = LineAligned::zeros(POS * cout * cin);
    for co in 0..cout {
        for ci in 0..cin {
            let k = &w[(co * cin + ci) * r * r..][..r * r];
            // t = G w: [A, R].
            let mut t = [[0f64; 5]; A];
            for (ti, gi) in t.iter_mut().zip(&T::G) {
                for (b, tv) in ti.iter_mut().enumerate().take(r) {
                    *tv = (0..r).map(|a| gi[a] * k[a * r + b] as f64).sum();
                }
            }
            let (panel, lane) = (co / CV, co % CV);
            for (i, ti) in t.iter().enumerate() {
                for (j, gj) in T::G.iter().enumerate() {
                    let v: f64 = (0..r).map(|b| ti[b] * gj[b]).sum();
                    u[(((i * A + j) * (cout / CV) + panel) * cin + ci) * CV + lane] = v as f32;
                }
            }
        }
    }
    u
}

/// Zero floats after each channel's phase planes, so that a group's loads at the last
/// tile slots stay inside the channel (they read past its last plane by at most the halo
/// and a group's lanes).
const SLACK: usize = 16;

/// How an image's tiles are laid out: tile `(ty, tx)` sits at slot `F = ty * wp + tx`
/// (the `wp - tx` slots past each row's last tile are padding), and the input is split into `M x M` phase planes
/// `[hp, wp]` (`x[r][c]` at phase `(r % M, c % M)`, position `(r / M, c / M)`), so that input
/// `(i, j)` of every tile is one fixed offset from its slot: consecutive slots read
/// consecutive floats.
#[derive(Clone, Copy)]
struct Layout {
    m: usize,
    ty: usize,
    tx: usize,
    hp: usize,
    wp: usize,
}

impl Layout {
    fn new<T: Algo>(g: &Geom) -> Self {
        let m = T::M;
        let halo = (A - 1) / m;
        let (ty, tx) = (g.ho().div_ceil(m), g.wo().div_ceil(m));
        Self {
            m,
            ty,
            tx,
            hp: ty + halo,
            wp: tx + halo,
        }
    }
    /// Floats per input channel in the phase layout.
    fn channel(&self) -> usize {
        self.m * self.m * self.hp * self.wp + SLACK
    }
    /// Tile slots per image.
    fn slots(&self) -> usize {
        self.ty * self.wp
    }
    /// Offset of tile input `(i, j)` from the slot, within a channel.
    fn tap(&self, i: usize, j: usize) -> usize {
        let (m, plane) = (self.m, self.hp * self.wp);
        ((i % m) * m + j % m) * plane + (i / m) * self.wp + j / m
    }
}

/// One image `[Cin, H, W]` into the phase layout `[Cin, channel]` (`out`'s padding is left
/// as it is: zeros from its allocation, as every image writes the same positions).
fn phase_image<T: Algo>(g: &Geom, lay: &Layout, x: &[f32], out: &mut [f32]) {
    let (m, plane, ch) = (T::M, lay.hp * lay.wp, lay.channel());
    for (xc, oc) in x.chunks_exact(g.hw()).zip(out.chunks_exact_mut(ch)) {
        for (r, row) in xc.chunks_exact(g.w).enumerate() {
            let base = (r % m) * m * plane + (r / m) * lay.wp;
            for pc in 0..m {
                let dst = &mut oc[base + pc * plane..][..lay.wp];
                for (d, &v) in dst.iter_mut().zip(row.iter().skip(pc).step_by(m)) {
                    *d = v;
                }
            }
        }
    }
}

fn run<T: Algo>(g: &Geom, x: &[f32], w: &[f32], b: &[f32], relu: bool) -> Vec<f32> {
    let (cin, cout, p) = (g.cin, g.cout, g.p());
    let u = transform_weights::<T>(g, w);
    let lay = Layout::new::<T>(g);
    let groups_per_unit = UNIT_TILES / LANES;
    let units_per_image = lay.slots().div_ceil(UNIT_TILES);
    let offsets: Vec<usize> = (0..cin).map(|ci| ci * UNIT_TILES).collect();
    let taps: [[usize; A]; A] = std::array::from_fn(|i| std::array::from_fn(|j| lay.tap(i, j)));
    let len = g.n * cout * p;
    // Every output is written below (all units, channels and tiles) before `set_len`.
    let mut y = Vec::<f32>::with_capacity(len);
    let yp = SharedMut(y.as_mut_ptr());
    let units = g.n * units_per_image;
    let chunks = (rayon::current_num_threads() * CHUNKS_PER_THREAD).min(units);
    (0..chunks).into_par_iter().for_each(|chunk| {
        // Scratch for the chunk's units: the current image in the phase layout, V `[POS,
        // Cin, slots]`, M `[POS, panels, slots, CV]`.
        let mut xph = LineAligned::zeros(cin * lay.channel());
        let mut image = None;
        let mut v = LineAligned::zeros(POS * cin * UNIT_TILES);
        let mut m = vec![[[0f32; CV]; NP]; POS * cout * UNIT_TILES / (CV * NP)];
        for unit in units * chunk / chunks..units * (chunk + 1) / chunks {
            let (n, s0) = (
                unit / units_per_image,
                (unit % units_per_image) * UNIT_TILES,
            );
            if image != Some(n) {
                phase_image::<T>(g, &lay, &x[n * cin * g.hw()..][..cin * g.hw()], &mut xph);
                image = Some(n);
            }
            let groups = (lay.slots() - s0).div_ceil(LANES).min(groups_per_unit);
            let slots = groups * LANES;
            // SAFETY: `available` (via `applies`) checked the CPU; loads stay inside
            // each channel (`SLACK`).
            unsafe { input_transform::<T>(&xph, lay.channel(), &taps, s0, groups, &mut v) };
            for pos in 0..POS {
                let vp = &v[pos * cin * UNIT_TILES..][..cin * UNIT_TILES];
                for panel in 0..cout / CV {
                    let up = &u[(pos * (cout / CV) + panel) * cin * CV..][..cin * CV];
                    let mp = &mut m[(pos * (cout / CV) + panel) * UNIT_TILES / NP..]
                        [..slots.div_ceil(NP)];
                    // SAFETY: `applies` checked the CPU; group t < UNIT_TILES / NP reads
                    // V[pos][ci][t * NP + px] (offsets ci * UNIT_TILES, ci < cin), inside
                    // the unit's V.
                    #[cfg(target_arch = "x86_64")]
                    unsafe {
                        gemm_groups(&offsets, vp.as_ptr(), up, mp)
                    };
                }
            }
            let m = m.as_flattened().as_flattened();
            // SAFETY: as above; the unit's tiles own their outputs in image n.
            unsafe {
                output_transform::<T>(g, &lay, m, b, relu, s0, groups, yp.get().add(n * cout * p))
            };
        }
    });
    // SAFETY: the units above wrote all `len` outputs.
    unsafe { y.set_len(len) };
    y
}
