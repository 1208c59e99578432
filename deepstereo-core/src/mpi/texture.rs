//! What [`Mpi::render`] samples: each plane as a premultiplied,
//! bordered texture with its empty blocks marked, and the runs of a row's rays that land
//! inside a plane's image.

#[cfg(doc)]
use super::Mpi;

/// A row of rays whose slopes `a` and `b` are each monotonic and finite and whose
/// `(R r)_z` share one sign: the rays that land inside a plane's image are one run.
pub(super) struct RowRuns<'a> {
    a: &'a [f64],
    b: &'a [f64],
    /// Whether `a`, `b` ascend (else they descend).
    a_up: bool,
    b_up: bool,
    rz_sign: f64,
}

impl<'a> RowRuns<'a> {
    /// `None` when the row lacks that shape.
    pub(super) fn of(a: &'a [f64], b: &'a [f64], rz: &[f64]) -> Option<Self> {
        let order = |v: &[f64]| -> Option<bool> {
            if v.iter().any(|x| !x.is_finite()) {
                return None;
            }
            let up = v.windows(2).all(|p| p[0] <= p[1]);
            let down = v.windows(2).all(|p| p[0] >= p[1]);
            (up || down).then_some(up)
        };
        let rz_sign = rz.first()?.signum();
        if rz.iter().any(|z| z.signum() != rz_sign || *z == 0.0) {
            return None;
        }
        Some(Self {
            a,
            b,
            a_up: order(a)?,
            b_up: order(b)?,
            rz_sign,
        })
    }

    /// The run of rays that may land inside the `w x h` image of the plane with map `m`
    /// ([`Mpi::plane_maps`]): a superset (its bounds widened by a millionth of a pixel)
    /// of those where `0 <= u <= w` and `0 <= v <= h`; empty when the plane lies behind.
    pub(super) fn inside(&self, m: &[f64; 5], w: f64, h: f64) -> std::ops::Range<usize> {
        if m[0] * self.rz_sign <= 0.0 {
            return 0..0;
        }
        let ra = run(self.a, self.a_up, m[1], m[2], w);
        let rb = run(self.b, self.b_up, m[3], m[4], h);
        ra.start.max(rb.start)..ra.end.min(rb.end).max(ra.start.max(rb.start))
    }
}

/// The run of the monotonic `v` (ascending when `up`) where `0 <= s v + o <= side`,
/// widened by a millionth of a pixel.
pub(super) fn run(v: &[f64], up: bool, s: f64, o: f64, side: f64) -> std::ops::Range<usize> {
    const SLACK: f64 = 1e-6;
    let (lo, hi) = (-SLACK, side + SLACK);
    if s == 0.0 {
        return match o >= lo && o <= hi {
            true => 0..v.len(),
            false => 0..0,
        };
    }
    // s v + o in [lo, hi]  <=>  v in [vlo, vhi] (the bounds swap when s < 0), widened
    // again for the division's rounding.
    let (p, q) = ((lo - o) / s, (hi - o) / s);
    let (vlo, vhi) = (p.min(q), p.max(q));
    let pad = 1e-12 * (1.0 + vlo.abs().max(vhi.abs()));
    let (vlo, vhi) = (vlo - pad, vhi + pad);
    let (start, end) = match up {
        true => (
            v.partition_point(|&x| x < vlo),
            v.partition_point(|&x| x <= vhi),
        ),
        false => (
            v.partition_point(|&x| x > vhi),
            v.partition_point(|&x| x >= vlo),
        ),
    };
    start..end.max(start)
}

/// A plane as [`Mpi::render`] samples it: the colour premultiplied by the alpha (so
/// bilinear sampling does not bleed the colour of transparent texels), and a border of
/// one texel that repeats the edge, so a sample never clamps: texel `(x, y)` of the
/// plane is `data[(y + 1) * stride + x + 1]`; and which blocks of it are empty, so that
/// sampling skips them (a baked plane is transparent over much of the image: on a
/// juicebox path, 45% of the samples were).
#[derive(Clone, Debug)]
pub(super) struct Texture {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) stride: usize,
    pub(super) data: Vec<[f32; 4]>,
    /// Per block of `data` (`1 << BLOCK_SHIFT` texels on a side; row-major, `blocks` per
    /// row): whether a bilinear sample whose top-left texel lies in the block can see a
    /// non-zero alpha (the block and the texel row and column after it).
    pub(super) occupied: Vec<bool>,
    pub(super) blocks: usize,
}

/// The side of [`Texture`]'s occupancy blocks, as a shift: 8 texels.
pub(super) const BLOCK_SHIFT: usize = 3;

impl Texture {
    /// From straight RGBA `[H, W, 4]` in [0, 1].
    pub(super) fn of(plane: &[f32], w: usize, h: usize) -> Self {
        let stride = w + 2;
        let texel = |x: usize, y: usize| {
            let t = &plane[(y * w + x) * 4..][..4];
            let [r, g, b, a] = [t[0], t[1], t[2], t[3]];
            [r * a, g * a, b * a, a]
        };
        let mut data = Vec::with_capacity(stride * (h + 2));
        for y in 0..h + 2 {
            let sy = y.saturating_sub(1).min(h - 1);
            data.extend((0..stride).map(|x| texel(x.saturating_sub(1).min(w - 1), sy)));
        }
        let (blocks, occupied) = occupancy(&data, stride, h + 2);
        Self {
            width: w,
            height: h,
            stride,
            data,
            occupied,
            blocks,
        }
    }

    /// The bilinear premultiplied RGBA at pixel coordinate `(u, v)` (centres at
    /// `i + 0.5`; edge pixels extend half a pixel); `None` outside the image, and where
    /// the four texels lie in an empty block ([`occupancy`]; the sample would be zero).
    #[inline]
    pub(super) fn sample(&self, u: f64, v: f64) -> Option<[f32; 4]> {
        if !(u >= 0.0 && v >= 0.0 && u <= self.width as f64 && v <= self.height as f64) {
            return None;
        }
        // In the bordered texture the texel centres sit at i - 0.5: fx, fy >= 0.5, so
        // truncating is the floor, and texels xi..=xi + 1, yi..=yi + 1 all exist.
        let (fx, fy) = (u + 0.5, v + 0.5);
        let (xi, yi) = (fx as usize, fy as usize);
        if !self.occupied[(yi >> BLOCK_SHIFT) * self.blocks + (xi >> BLOCK_SHIFT)] {
            return None;
        }
        let (ax, ay) = ((fx - xi as f64) as f32, (fy - yi as f64) as f32);
        let i = yi * self.stride + xi;
        let q = &self.data[i..i + self.stride + 2];
        let (bx, by) = (1.0 - ax, 1.0 - ay);
        let (wa, wb, wc, wd) = (bx * by, ax * by, bx * ay, ax * ay);
        let (pa, pb, pc, pd) = (q[0], q[1], q[self.stride], q[self.stride + 1]);
        let mut out = [0f32; 4];
        for (c, o) in out.iter_mut().enumerate() {
            *o = pa[c] * wa + pb[c] * wb + pc[c] * wc + pd[c] * wd;
        }
        Some(out)
    }
}

/// Blocks per row and, per block of `1 << BLOCK_SHIFT` texels on a side (row-major), whether
/// a texel of the block or of the row and column after it has a non-zero alpha: a
/// bilinear footprint whose top-left texel lies in a block that is not occupied samples
/// only zeros (premultiplied, so colour too).
fn occupancy(data: &[[f32; 4]], stride: usize, rows: usize) -> (usize, Vec<bool>) {
    let side = 1 << BLOCK_SHIFT;
    let (bw, bh) = (stride.div_ceil(side), rows.div_ceil(side));
    let mut occupied = vec![false; bw * bh];
    for (i, _) in data.iter().enumerate().filter(|(_, t)| t[3] > 0.0) {
        let (x, y) = (i % stride, i / stride);
        // Blocks whose footprints reach texel (x, y): its own, and the one before it in
        // x and y when the texel opens its block's row or column.
        for by in (y.saturating_sub(1) >> BLOCK_SHIFT)..=(y >> BLOCK_SHIFT) {
            for bx in (x.saturating_sub(1) >> BLOCK_SHIFT)..=(x >> BLOCK_SHIFT) {
                occupied[by * bw + bx] = true;
            }
        }
    }
    (bw, occupied)
}
