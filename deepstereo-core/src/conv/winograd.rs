//! Winograd minimal-filtering forward (f32, AVX2 and FMA) for the 3x3 and 5x5 layers with
//! output channels a multiple of [`CV`]: F(2x2, 5x5) and F(4x4, 3x3), both on 6x6 input
//! tiles (A = 6), so an output tile costs 36 products per input channel and output channel
//! instead of 100 (5x5) or 144 (3x3).
//!
//! With `U = G w G^T` (weights, once per call, in f64), `V = B^T d B` (each input tile `d`)
//! and `Y = A^T M A` for `M[pos][co] = sum_ci U[pos][co][ci] V[pos][ci]`, the 36 products
//! `M[pos]` are 36 small matrix products, run by `direct_cv.rs`'s tile kernel (16 output
//! channels x 6 tiles, one tap per input channel). The transforms come from Toom-Cook on
//! the points 0, 1, -1, 1/2, -1/2 (5x5) or 0, 1, -1, 1/2, -2 (3x3) and infinity
//! (`B^T = (V^-1)^T` for the Vandermonde matrix `V` of the points, `G` and `A^T` their
//! evaluation matrices); on random data their f32 rounding error was 1.2e-7 and 2.5e-7 of
//! the sum of the products' magnitudes, about that of a direct f32 sum.
//!
//! Work units are runs of up to [`UNIT_TILES`] tiles of one image: transform the unit's
//! input tiles into `V[pos][ci][t]`, multiply into `M[pos][co][t]`, transform back with
//! bias and ReLU into the output (tiles that overhang the output's edge read zeros and drop
//! the outputs past it).

use super::direct::{available, kernels_allowed, Kernels, LineAligned};
#[cfg(target_arch = "x86_64")]
use super::direct_cv::gemm_groups;
use super::direct_cv::{CV, NP};
use super::im2col::{Geom, SharedMut};
use rayon::prelude::*;

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
/// channel, the products' per output channel (with 16 outputs the direct kernel was 1.5x
/// faster on the `paper` layers).
const MIN_COUT: usize = 32;
/// Fewest input channels for this path (below it the transforms cost more than they save).
const MIN_CIN: usize = 8;

/// One algorithm F(M x M, R x R) on `A x A` tiles: its transforms as constants, so that
/// the transform loops compile to straight-line code without the zero terms.
trait Algo {
    /// Outputs per tile side.
    const M: usize;
    /// Kernel side.
    const R: usize;
    /// `B^T` (`[A, A]`).
    const BT: [[f32; A]; A];
    /// `G` (`[A, R]`, columns past `R` zero).
    const G: [[f64; 5]; A];
    /// `A^T` (`[M, A]`, rows past `M` unused).
    const AT: [[f32; A]; 4];
}

/// F(2x2, 5x5), points 0, 1, -1, 1/2, -1/2, infinity.
struct F25;

impl Algo for F25 {
    const M: usize = 2;
    const R: usize = 5;
    const BT: [[f32; A]; A] = [
        [1.0, 0.0, -5.0, 0.0, 4.0, 0.0],
        [0.0, -1.0 / 6.0, -1.0 / 6.0, 2.0 / 3.0, 2.0 / 3.0, 0.0],
        [0.0, 1.0 / 6.0, -1.0 / 6.0, -2.0 / 3.0, 2.0 / 3.0, 0.0],
        [0.0, 4.0 / 3.0, 8.0 / 3.0, -4.0 / 3.0, -8.0 / 3.0, 0.0],
        [0.0, -4.0 / 3.0, 8.0 / 3.0, 4.0 / 3.0, -8.0 / 3.0, 0.0],
        [0.0, 0.25, 0.0, -1.25, 0.0, 1.0],
    ];
    const G: [[f64; 5]; A] = [
        [1.0, 0.0, 0.0, 0.0, 0.0],
        [1.0, 1.0, 1.0, 1.0, 1.0],
        [1.0, -1.0, 1.0, -1.0, 1.0],
        [1.0, 0.5, 0.25, 0.125, 0.0625],
        [1.0, -0.5, 0.25, -0.125, 0.0625],
        [0.0, 0.0, 0.0, 0.0, 1.0],
    ];
    const AT: [[f32; A]; 4] = [
        [1.0, 1.0, 1.0, 1.0, 1.0, 0.0],
        [0.0, 1.0, -1.0, 0.5, -0.5, 1.0],
        [0.0; A],
        [0.0; A],
    ];
}

/// F(4x4, 3x3), points 0, 1, -1, 1/2, -2, infinity.
struct F43;

impl Algo for F43 {
    const M: usize = 4;
    const R: usize = 3;
    const BT: [[f32; A]; A] = [
        [1.0, -1.5, -2.0, 1.5, 1.0, 0.0],
        [0.0, -1.0 / 3.0, 1.0 / 6.0, 5.0 / 6.0, 1.0 / 3.0, 0.0],
        [0.0, -1.0 / 3.0, 5.0 / 6.0, -1.0 / 6.0, -1.0 / 3.0, 0.0],
        [
            0.0,
            32.0 / 15.0,
            16.0 / 15.0,
            -32.0 / 15.0,
            -16.0 / 15.0,
            0.0,
        ],
        [0.0, 1.0 / 30.0, -1.0 / 15.0, -1.0 / 30.0, 1.0 / 15.0, 0.0],
        [0.0, 1.0, -1.5, -2.0, 1.5, 1.0],
    ];
    const G: [[f64; 5]; A] = [
        [1.0, 0.0, 0.0, 0.0, 0.0],
        [1.0, 1.0, 1.0, 0.0, 0.0],
        [1.0, -1.0, 1.0, 0.0, 0.0],
        [1.0, 0.5, 0.25, 0.0, 0.0],
        [1.0, -2.0, 4.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0, 0.0],
    ];
    const AT: [[f32; A]; 4] = [
        [1.0, 1.0, 1.0, 1.0, 1.0, 0.0],
        [0.0, 1.0, -1.0, 0.5, -2.0, 0.0],
        [0.0, 1.0, 1.0, 0.25, 4.0, 0.0],
        [0.0, 1.0, -1.0, 0.125, -8.0, 1.0],
    ];
}

/// Whether [`forward`] runs this layer (f32 callers only).
pub(crate) fn applies(g: &Geom) -> bool {
    available()
        && kernels_allowed() == Kernels::Auto
        && g.kh == g.kw
        && matches!(g.kh, 3 | 5)
        && g.cout.is_multiple_of(CV)
        && g.cout >= MIN_COUT
        && g.cin >= MIN_CIN
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
/// (slots with `tx >= tx` are padding), and the input is split into `M x M` phase planes
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

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// `[e(0), .., e(5)]` (or `e(0)..e(3)`), expanded in place: constant indices let the
/// transforms compile to straight-line code with their coefficients folded.
macro_rules! arr6 {
    (|$i:ident| $e:expr) => {
        [
            {
                let $i = 0;
                $e
            },
            {
                let $i = 1;
                $e
            },
            {
                let $i = 2;
                $e
            },
            {
                let $i = 3;
                $e
            },
            {
                let $i = 4;
                $e
            },
            {
                let $i = 5;
                $e
            },
        ]
    };
}
macro_rules! arr4 {
    (|$i:ident| $e:expr) => {
        [
            {
                let $i = 0;
                $e
            },
            {
                let $i = 1;
                $e
            },
            {
                let $i = 2;
                $e
            },
            {
                let $i = 3;
                $e
            },
        ]
    };
}

/// `sum_i row[i] * v[i]`, skipping zero coefficients (constants after inlining).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn dot6(row: &[f32; A], v: &[__m256; A]) -> __m256 {
    let mut acc = _mm256_setzero_ps();
    for i in 0..A {
        if row[i] != 0.0 {
            acc = _mm256_fmadd_ps(_mm256_set1_ps(row[i]), v[i], acc);
        }
    }
    acc
}

/// `V[pos][ci][slot] = (B^T d B)[pos]` for the unit's `groups` groups of [`LANES`] slots
/// from slot `s0` (`d` the tile's `A x A` inputs, at `taps[i][j]` from its slot).
///
/// # Safety
/// AVX2 and FMA present; `x` holds `cin` channels of `channel` floats in the phase layout.
#[target_feature(enable = "avx2,fma")]
unsafe fn input_transform<T: Algo>(
    x: &[f32],
    channel: usize,
    taps: &[[usize; A]; A],
    s0: usize,
    groups: usize,
    v: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    {
        let cin = x.len() / channel;
        assert!(v.len() >= POS * cin * UNIT_TILES && groups * LANES <= UNIT_TILES);
        let last_tap = taps.iter().flatten().copied().max().unwrap_or(0);
        assert!(s0 + groups * LANES + last_tap <= channel);
        let (vp, xp) = (v.as_mut_ptr(), x.as_ptr());
        // Channel by channel, so that a channel's rows of V (36 x 3 lines) stay in L1.
        for ci in 0..cin {
            for grp in 0..groups {
                // In bounds: asserted above (the last load ends at the last slot + tap).
                let xc = xp.add(ci * channel + s0 + grp * LANES);
                // Columns of d through B^T: tmp[j][p] = sum_i B^T[p][i] d[i][j].
                let tmp: [[__m256; A]; A] = arr6!(|j| {
                    let col = arr6!(|i| _mm256_loadu_ps(xc.add(taps[i][j])));
                    arr6!(|pi| dot6(&T::BT[pi], &col))
                });
                let out = vp.add(ci * UNIT_TILES + grp * LANES);
                let _ = arr6!(|pi| {
                    let row = arr6!(|j| tmp[j][pi]);
                    arr6!(|q| _mm256_storeu_ps(
                        out.add((pi * A + q) * cin * UNIT_TILES),
                        dot6(&T::BT[q], &row)
                    ))
                });
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (x, channel, taps, s0, groups, v);
}

/// `y = act(A^T M A + bias)` for the unit's slots, eight channels at a time (`M` is
/// `[POS, panels, slots, CV]`), written to the outputs inside the image (`y` addresses
/// image n's `[Cout, Ho, Wo]`; padding slots are skipped).
///
/// # Safety
/// AVX2 and FMA present; no other thread writes these tiles' outputs.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma")]
unsafe fn output_transform<T: Algo>(
    g: &Geom,
    lay: &Layout,
    m: &[f32],
    b: &[f32],
    relu: bool,
    s0: usize,
    groups: usize,
    y: *mut f32,
) {
    #[cfg(target_arch = "x86_64")]
    {
        let (cout, ho, wo, mm, p) = (g.cout, g.ho(), g.wo(), T::M, g.p());
        let panels = cout / CV;
        let zero = _mm256_setzero_ps();
        // Each slot's first output (row, column), or none for padding slots.
        let mut first = [None; UNIT_TILES];
        for (slot, f) in first.iter_mut().enumerate().take(groups * LANES) {
            let (ty, tx) = ((s0 + slot) / lay.wp, (s0 + slot) % lay.wp);
            *f = (ty < lay.ty && tx < lay.tx).then_some((ty * mm, tx * mm));
        }
        assert!(m.len() >= POS * cout * UNIT_TILES && b.len() >= cout);
        let mp = m.as_ptr();
        // Eight channels at a time, slot after slot: M is read in runs of lines.
        for c8 in (0..cout).step_by(LANES) {
            let (panel, h) = (c8 / CV, c8 % CV);
            let bias = _mm256_loadu_ps(b[c8..c8 + LANES].as_ptr());
            for (slot, f) in first.iter().enumerate().take(groups * LANES) {
                let Some((r0, c0)) = *f else { continue };
                let (rows, cols) = (mm.min(ho - r0), mm.min(wo - c0));
                // In bounds: asserted above (pos < POS, panel < cout / CV, slot < UNIT_TILES).
                let at = mp.add((panel * UNIT_TILES + slot) * CV + h);
                // tmp[j][a] = sum_i A^T[a][i] M[i][j].
                let tmp: [[__m256; 4]; A] = arr6!(|j| {
                    let col =
                        arr6!(|i| _mm256_loadu_ps(at.add((i * A + j) * panels * UNIT_TILES * CV)));
                    arr4!(|a| dot6(&T::AT[a], &col))
                });
                let _ = arr4!(|a| if a < rows {
                    let row = arr6!(|j| tmp[j][a]);
                    let _ = arr4!(|bq| if bq < cols {
                        let o = _mm256_add_ps(dot6(&T::AT[bq], &row), bias);
                        let o = if relu { _mm256_max_ps(o, zero) } else { o };
                        let mut vals = [0f32; LANES];
                        _mm256_storeu_ps(vals.as_mut_ptr(), o);
                        let dst = y.add(c8 * p + (r0 + a) * wo + c0 + bq);
                        for (l, &v) in vals.iter().enumerate() {
                            *dst.add(l * p) = v;
                        }
                    });
                });
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (g, lay, m, b, relu, s0, groups, y);
}
