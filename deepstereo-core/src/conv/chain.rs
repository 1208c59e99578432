//! Inference-only chains of small convolutions evaluated block by block: [`PX`] pixels at
//! a time, every layer of the chain before the next block, intermediate activations in a
//! per-thread scratch buffer that stays in L1/L2 (they never go to memory). No gradients:
//! training runs the layers one by one through [`super::op`].
//!
//! - [`depth_head`]: the selection tower's convolutions across depth and its softmax,
//!   reading the 2D tower's `[B, D, C, H, W]` output directly (no transpose or padding
//!   copies; zero rows stand for the padding along depth);
//! - [`pointwise_colours`]: a colour tower of 1x1 convolutions and its output layer
//!   (with the skip input), reading the tile's pixels straight out of the level-0 input
//!   (no crop copy, no concatenation).
//!
//! A block's scratch holds rows of `C x PX` floats (channel-major, pixels innermost); a
//! layer with `k` taps along rows writes output row `r` from input rows `r .. r + k`
//! through `direct.rs`'s tile (same tap order, so the sums equal the layer-by-layer path's).

use super::direct::{pack, store_tile, LineAligned, MR, NC};
use super::{plan, Conv2d};
use crate::cpu::{softmax_columns, SharedMut};
use candle_core::{bail, Result, Tensor};
use rayon::prelude::*;

/// Pixels per block: one tile of the kernel.
const PX: usize = NC;
/// Work items wanted per thread (blocks are grouped into this many runs per thread).
const RUNS_PER_THREAD: usize = 8;

/// Runs `f(block)` for blocks `0..n` on all threads, each run of blocks with its own
/// scratch from `init`.
fn par_blocks<S>(n: usize, init: impl Fn() -> S + Sync, f: impl Fn(&mut S, usize) + Sync) {
    if n == 0 {
        return;
    }
    let runs = (rayon::current_num_threads() * RUNS_PER_THREAD).clamp(1, n.max(1));
    let per = n.div_ceil(runs);
    (0..n.div_ceil(per)).into_par_iter().for_each(|run| {
        let mut s = init();
        for blk in run * per..((run + 1) * per).min(n) {
            f(&mut s, blk);
        }
    });
}

/// The f32 elements of a contiguous CPU tensor, passed to `f`.
fn with_data<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> Result<R>) -> Result<R> {
    let t = t.contiguous()?;
    let (st, l) = t.storage_and_layout();
    f(super::op::data::<f32>(&st, l)?)
}

/// A convolution along the rows of a block's scratch (`k` taps), mixing channels.
struct Layer {
    wp: LineAligned,
    bias: Vec<f32>,
    cin: usize,
    cout: usize,
    k: usize,
    relu: bool,
}

impl Layer {
    /// From a `[C_out, C_in, k, 1]` convolution.
    fn new(conv: &Conv2d, relu: bool) -> Result<Self> {
        let (cout, cin, k, kw) = conv.weight().dims4()?;
        if kw != 1 {
            bail!("fused chain: expected a k x 1 kernel, got {k} x {kw}");
        }
        let w = conv.weight().flatten_all()?.to_vec1::<f32>()?;
        Ok(Self {
            wp: pack(&w, cout, cin * k, MR),
            bias: conv.bias().to_vec1::<f32>()?,
            cin,
            cout,
            k,
            relu,
        })
    }

    /// Tap `c * k + t` (the weights' order) reads row `t`, channel `c` of an input whose
    /// rows are `cin * PX` floats apart.
    fn offsets(&self) -> Vec<usize> {
        let stride = self.cin * PX;
        (0..self.cin)
            .flat_map(|c| (0..self.k).map(move |t| t * stride + c * PX))
            .collect()
    }

    /// Output rows `0..rows` (`cout * PX` floats apart from `y`) from input rows
    /// `0..rows + k - 1` at `x`.
    ///
    /// # Safety
    /// [`available`]; `x` holds `(rows + k - 1) * cin * PX` floats, `y` `rows * cout * PX`;
    /// `offs` is [`Self::offsets`].
    unsafe fn run(&self, offs: &[usize], x: *const f32, y: *mut f32, rows: usize) {
        let kk = self.cin * self.k;
        for r in 0..rows {
            for panel in 0..self.cout.div_ceil(MR) {
                let mr = (self.cout - panel * MR).min(MR);
                store_tile(
                    mr,
                    offs,
                    x.add(r * self.cin * PX),
                    &self.wp[panel * kk * MR..][..kk * MR],
                    &self.bias[panel * MR..][..mr],
                    y.add((r * self.cout + panel * MR) * PX),
                    PX,
                    self.relu,
                );
            }
        }
    }
}

/// Selection probabilities `[B, D, H * W]` from the 2D selection features `s`
/// (`[B * D, C, H, W]`): the depth convolutions `convs` (`[C_out, C_in, k, 1]`, zero
/// padding of `k / 2` planes on both sides, ReLU between them) and
/// `softmax_D(tanh(x) exp(log_scale))`. `None` where the fused kernels do not run (not
/// f32 on a CPU with AVX2, or nothing to compute); the caller then runs the layers one by
/// one.
pub fn depth_head(
    s: &Tensor,
    planes: usize,
    convs: &[Conv2d],
    log_scale: &Tensor,
) -> Result<Option<Tensor>> {
    let (n, c, h, w) = s.dims4()?;
    if !plan::chain(&[s, log_scale]) || planes == 0 || n * h * w == 0 {
        return Ok(None);
    }
    let (b, d, p) = (n / planes, planes, h * w);
    if b * d != n || convs.is_empty() {
        bail!("depth_head: {n} planes are not batches of {planes}, or no convolutions");
    }
    let layers = depth_layers(c, convs)?;
    let Some(ls) = log_scale.flatten_all()?.to_vec1::<f32>()?.first().copied() else {
        bail!("depth_head: empty log_scale");
    };
    let a = ls.exp();
    let offs: Vec<Vec<usize>> = layers.iter().map(Layer::offsets).collect();
    // Layer i reads buffer i: D rows and k_i / 2 zero rows above and below; the last
    // layer writes D rows of one channel.
    let pads: Vec<usize> = layers.iter().map(|l| l.k / 2).collect();
    let sizes: Vec<usize> = layers
        .iter()
        .zip(&pads)
        .map(|(l, &pd)| (d + 2 * pd) * l.cin * PX)
        .chain([d * PX])
        .collect();
    let blocks = p.div_ceil(PX);
    let mut out = vec![0f32; b * d * p];
    let op = SharedMut(out.as_mut_ptr());
    with_data(s, |s| {
        let init = || {
            let bufs: Vec<LineAligned> = sizes.iter().map(|&n| LineAligned::zeros(n)).collect();
            (bufs, vec![0f32; d * PX])
        };
        par_blocks(b * blocks, init, |(bufs, soft), blk| {
            let (bi, q0) = (blk / blocks, (blk % blocks) * PX);
            let np = PX.min(p - q0);
            let src = &s[bi * d * c * p..][..d * c * p];
            load_columns(src, (c, p), (q0, np), &mut bufs[0][pads[0] * c * PX..]);
            for (i, l) in layers.iter().enumerate() {
                let (lo, hi) = bufs.split_at_mut(i + 1);
                let pd = pads.get(i + 1).copied().unwrap_or(0);
                // SAFETY: `fast` checked the CPU; buffer i holds (d + 2 pad_i) rows of
                // cin_i channels, buffer i + 1 rows pd .. pd + d of cout_i channels.
                unsafe {
                    let y = hi[0].as_mut_ptr().add(pd * l.cout * PX);
                    l.run(&offs[i], lo[i].as_ptr(), y, d);
                }
            }
            // SAFETY: `soft` holds d * PX values; columns 0..np.
            unsafe {
                let logits = &bufs[layers.len()][..];
                softmax_columns(logits, soft.as_mut_ptr(), a, (d, PX), 0, np);
            }
            for (row, sr) in soft.chunks_exact(PX).enumerate() {
                // SAFETY: block (bi, q0) owns columns q0 .. q0 + np of batch item bi.
                unsafe {
                    let dst = op.get().add((bi * d + row) * p + q0);
                    std::ptr::copy_nonoverlapping(sr.as_ptr(), dst, np);
                }
            }
        });
        Ok(())
    })?;
    Tensor::from_vec(out, (b, d, p), s.device()).map(Some)
}

/// The layers of [`depth_head`] (ReLU after all but the last), checked to chain from `c`
/// channels to 1.
fn depth_layers(c: usize, convs: &[Conv2d]) -> Result<Vec<Layer>> {
    let last = convs.len() - 1;
    let layers = convs
        .iter()
        .enumerate()
        .map(|(i, cv)| Layer::new(cv, i < last))
        .collect::<Result<Vec<_>>>()?;
    let chained = layers.windows(2).all(|l| l[0].cout == l[1].cin);
    if layers[0].cin != c || !chained || layers[last].cout != 1 {
        bail!("depth_head: convolutions do not chain from {c} channels to 1");
    }
    Ok(layers)
}

/// Columns `q0..q0 + np` of every plane of `src` (`[D, c, p]`) into `dst`, one row of
/// [`PX`] per plane and channel (the rest of each row zeroed).
fn load_columns(src: &[f32], (c, p): (usize, usize), (q0, np): (usize, usize), dst: &mut [f32]) {
    for (row, plane) in src.chunks_exact(c * p).enumerate() {
        for (ch, x) in plane.chunks_exact(p).enumerate() {
            let d = &mut dst[(row * c + ch) * PX..][..PX];
            d[..np].copy_from_slice(&x[q0..q0 + np]);
            d[np..].fill(0.0);
        }
    }
}

/// The colours `[N, 3, th, tw]` of a colour tower of 1x1 convolutions (`convs`, ReLU
/// after each) and its output layer `out` (no ReLU; its input the last features and,
/// when `skip`, the tile's own input channels after them), on the tile's pixels of the
/// level-0 input `x` (`[N, C, H, W]`, the tile at rows and columns `crop ..`). `None`
/// where the fused kernels do not run.
pub fn pointwise_colours(
    x: &Tensor,
    crop: usize,
    tile: (usize, usize),
    convs: &[&Conv2d],
    out: &Conv2d,
    skip: bool,
) -> Result<Option<Tensor>> {
    pointwise_run(x, crop, tile, convs, out, skip, false)
}

/// A chain of 1x1 convolutions with a ReLU after every one, the last included, over the
/// whole of `x` `[N, C, H, W]` -> `[N, C_out, H, W]` (the any-number-of-views family's
/// per-view encoder when rendering); `None` where the fused kernels do not run.
pub fn pointwise_chain(x: &Tensor, convs: &[&Conv2d]) -> Result<Option<Tensor>> {
    let (_, _, h, w) = x.dims4()?;
    match convs.split_last() {
        Some((last, first)) if !first.is_empty() => {
            pointwise_run(x, 0, (h, w), first, last, false, true)
        }
        _ => Ok(None),
    }
}

fn pointwise_run(
    x: &Tensor,
    crop: usize,
    (th, tw): (usize, usize),
    convs: &[&Conv2d],
    out: &Conv2d,
    skip: bool,
    head_relu: bool,
) -> Result<Option<Tensor>> {
    let (n, c, h, w) = x.dims4()?;
    if !plan::chain(&[x]) || n * th * tw == 0 {
        return Ok(None);
    }
    if crop + th > h || crop + tw > w || convs.is_empty() {
        bail!("pointwise_colours: a {th}x{tw} tile at {crop} does not fit {h}x{w}");
    }
    let (layers, head) = pointwise_layers(c, convs, (out, head_relu), skip)?;
    let f = layers[layers.len() - 1].cout;
    let (p, cout) = (th * tw, head.cout);
    // Scratch: `cat` = [features f; input c] (the output layer's input), two ping-pong
    // buffers for the layers in between, and the output block.
    let widest = layers.iter().map(|l| l.cout).max().unwrap_or(f);
    let offs: Vec<Vec<usize>> = layers.iter().map(Layer::offsets).collect();
    let head_offs = head.offsets();
    let blocks = p.div_ceil(PX);
    let mut y = vec![0f32; n * cout * p];
    let yp = SharedMut(y.as_mut_ptr());
    with_data(x, |x| {
        let init = || {
            let cat = LineAligned::zeros((f + c) * PX);
            let pp = [
                LineAligned::zeros(widest * PX),
                LineAligned::zeros(widest * PX),
            ];
            (cat, pp, LineAligned::zeros(cout * PX))
        };
        par_blocks(n * blocks, init, |(cat, pp, yb), blk| {
            let (ni, q0) = (blk / blocks, (blk % blocks) * PX);
            let np = PX.min(p - q0);
            let plane = &x[ni * c * h * w..][..c * h * w];
            gather_block(plane, (c, h, w), (crop, tw), (q0, np), &mut cat[f * PX..]);
            // SAFETY: `fast` checked the CPU; every buffer holds its layer's channels x
            // PX; the first layer reads `cat`'s input part, the last writes its features.
            unsafe {
                let mut src = cat.as_ptr().add(f * PX);
                for (i, l) in layers.iter().enumerate() {
                    let dst = if i + 1 == layers.len() {
                        cat.as_mut_ptr()
                    } else {
                        pp[i % 2].as_mut_ptr()
                    };
                    l.run(&offs[i], src, dst, 1);
                    src = dst;
                }
                // [features; input] or the features alone (`head.cin` channels of `cat`).
                head.run(&head_offs, cat.as_ptr(), yb.as_mut_ptr(), 1);
                for ch in 0..cout {
                    let dst = yp.get().add((ni * cout + ch) * p + q0);
                    std::ptr::copy_nonoverlapping(yb.as_ptr().add(ch * PX), dst, np);
                }
            }
        });
        Ok(())
    })?;
    Tensor::from_vec(y, (n, cout, th, tw), x.device()).map(Some)
}

/// The layers of [`pointwise_run`] (each with ReLU) and its output layer (ReLU where
/// `head_relu`), checked to be 1x1 convolutions that chain from `c` channels, the output
/// layer reading the last features and, with `skip`, the input after them.
fn pointwise_layers(
    c: usize,
    convs: &[&Conv2d],
    (out, head_relu): (&Conv2d, bool),
    skip: bool,
) -> Result<(Vec<Layer>, Layer)> {
    let layers = convs
        .iter()
        .map(|cv| Layer::new(cv, true))
        .collect::<Result<Vec<_>>>()?;
    let head = Layer::new(out, head_relu)?;
    let f = layers[layers.len() - 1].cout;
    let chained = layers.windows(2).all(|l| l[0].cout == l[1].cin);
    let head_in = f + if skip { c } else { 0 };
    let pointwise = layers.iter().chain([&head]).all(|l| l.k == 1);
    if layers[0].cin != c || !chained || head.cin != head_in || !pointwise {
        bail!("pointwise_colours: 1x1 convolutions do not chain from {c} channels");
    }
    Ok((layers, head))
}

/// Pixels `q0..q0 + np` of the `th x tw` tile at `(crop, crop)` of `plane` `[c, h, w]`,
/// row run by row run, into `dst` (`c` rows of [`PX`]; the rest of each row zeroed).
fn gather_block(
    plane: &[f32],
    (c, h, w): (usize, usize, usize),
    (crop, tw): (usize, usize),
    (q0, np): (usize, usize),
    dst: &mut [f32],
) {
    let mut q = q0;
    while q < q0 + np {
        let (r, col) = (q / tw, q % tw);
        let run = (tw - col).min(q0 + np - q);
        let src = (r + crop) * w + col + crop;
        for ch in 0..c {
            let d = &mut dst[ch * PX + q - q0..][..run];
            d.copy_from_slice(&plane[ch * h * w + src..][..run]);
        }
        q += run;
    }
    for ch in 0..c {
        dst[ch * PX + np..(ch + 1) * PX].fill(0.0);
    }
}
