//! The convolution as a candle `CustomOp3` `(x, weight, bias) -> y`, whose backward calls
//! the kernels directly.

use super::im2col::Geom;
use super::plan::{self, Backward};
use super::{direct_grad, kernels};
use candle_core::{
    bail, CpuStorage, CustomOp3, DType, Layout, Result, Shape, Storage, Tensor, WithDType,
};

/// Whether [`conv2d`] runs these inputs (CPU, f32 or f64); otherwise use candle's conv2d.
pub(crate) fn supported(x: &Tensor, w: &Tensor) -> bool {
    x.device().is_cpu() && matches!(x.dtype(), DType::F32 | DType::F64) && w.dtype() == x.dtype()
}

/// `act(conv(x, w) + b)`: x `[N, Cin, H, W]`, w `[Cout, Cin, kh, kw]`, b `[Cout]`, act ReLU
/// when `relu`, else identity. Valid padding, stride 1.
pub(crate) fn conv2d(x: &Tensor, w: &Tensor, b: &Tensor, relu: bool) -> Result<Tensor> {
    let g = geom(x.dims(), w.dims())?;
    if b.dims() != [g.cout] {
        bail!(
            "conv2d: bias {:?} does not match weight {:?}",
            b.dims(),
            w.dims()
        );
    }
    x.contiguous()?
        .apply_op3(&w.contiguous()?, &b.contiguous()?, ConvOp { relu })
}

fn geom(x: &[usize], w: &[usize]) -> Result<Geom> {
    let (&[n, cin, h, wd], &[cout, wcin, kh, kw]) = (x, w) else {
        bail!("conv2d: expected 4D input and weight, got {x:?} and {w:?}")
    };
    if wcin != cin || kh == 0 || kw == 0 || kh > h || kw > wd {
        bail!("conv2d: input {x:?} does not fit weight {w:?}");
    }
    Ok(Geom {
        n,
        cin,
        h,
        w: wd,
        cout,
        kh,
        kw,
    })
}

struct ConvOp {
    relu: bool,
}

/// The contiguous elements of a CPU tensor's storage.
pub(super) fn data<'a, T: WithDType>(s: &'a Storage, l: &Layout) -> Result<&'a [T]> {
    let (Storage::Cpu(cpu), Some((a, b))) = (s, l.contiguous_offsets()) else {
        bail!("conv2d: expected a contiguous CPU tensor")
    };
    Ok(&cpu.as_slice::<T>()?[a..b])
}

type Grads = (Option<Tensor>, Option<Tensor>, Option<Tensor>);

/// What a backward kernel returns: `dx` when asked for, `dw`, `db`.
type Raw<T> = (Option<Vec<T>>, Vec<T>, Vec<T>);

impl ConvOp {
    /// Runs `f(g, x, w, y, dy)` on the tensors' CPU slices (`y` empty without ReLU, whose
    /// mask is all the backward reads of it) and wraps the gradients that are tracked.
    fn bwd_with<T: WithDType>(
        &self,
        (x, w, b, y, dy): (&Tensor, &Tensor, &Tensor, &Tensor, &Tensor),
        f: impl FnOnce(&Geom, &[T], &[T], &[T], &[T]) -> Raw<T>,
    ) -> Result<Grads> {
        let g = geom(x.dims(), w.dims())?;
        let (dx, dw, db) = {
            let (xs, xl) = x.storage_and_layout();
            let (ws, wl) = w.storage_and_layout();
            let (ys, yl) = y.storage_and_layout();
            let (ds, dl) = dy.storage_and_layout();
            let y = if self.relu { data::<T>(&ys, yl)? } else { &[] };
            f(
                &g,
                data::<T>(&xs, xl)?,
                data::<T>(&ws, wl)?,
                y,
                data::<T>(&ds, dl)?,
            )
        };
        let dev = x.device();
        let dx = dx
            .map(|v| Tensor::from_vec(v, x.shape(), dev))
            .transpose()?;
        let dw = w
            .track_op()
            .then(|| Tensor::from_vec(dw, w.shape(), dev))
            .transpose()?;
        let db = b
            .track_op()
            .then(|| Tensor::from_vec(db, b.shape(), dev))
            .transpose()?;
        Ok((dx, dw, db))
    }

    /// The im2col path's backward.
    fn bwd_typed<T: WithDType>(
        &self,
        t: (&Tensor, &Tensor, &Tensor, &Tensor, &Tensor),
    ) -> Result<Grads> {
        let (need_dx, need_dw) = (t.0.track_op(), t.1.track_op());
        self.bwd_with::<T>(t, |g, x, w, y, dy| {
            let r = kernels::backward(g, x, w, y, dy, self.relu, need_dx, need_dw);
            (r.dx, r.dw, r.db)
        })
    }

    /// Wide layers: the input gradient by [`direct_grad::input_grad`] (Winograd), the
    /// weight and bias gradients by the im2col path.
    fn bwd_split(&self, t: (&Tensor, &Tensor, &Tensor, &Tensor, &Tensor)) -> Result<Grads> {
        self.bwd_with::<f32>(t, |g, x, w, y, dy| {
            let dx = direct_grad::input_grad(g, w, y, dy, self.relu);
            let r = kernels::backward(g, x, w, y, dy, self.relu, false, true);
            (Some(dx), r.dw, r.db)
        })
    }

    /// [`direct_grad::backward`] (f32, AVX2 and FMA).
    fn bwd_direct(&self, t: (&Tensor, &Tensor, &Tensor, &Tensor, &Tensor)) -> Result<Grads> {
        let need_dx = t.0.track_op();
        self.bwd_with::<f32>(t, |g, x, w, y, dy| {
            direct_grad::backward(g, x, w, y, dy, self.relu, need_dx)
        })
    }
}

impl CustomOp3 for ConvOp {
    fn name(&self) -> &'static str {
        "deepstereo-conv2d"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bs: &CpuStorage,
        bl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = geom(xl.dims(), wl.dims())?;
        let shape = Shape::from((g.n, g.cout, g.ho(), g.wo()));
        let _timer = CallTimer::start(g, "forward", 1.0);
        fn slice<'a, T: WithDType>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [T]> {
            match l.contiguous_offsets() {
                Some((a, b)) => Ok(&s.as_slice::<T>()?[a..b]),
                None => bail!("conv2d: expected contiguous tensors"),
            }
        }
        let y = match xs {
            CpuStorage::F32(_) => CpuStorage::F32(plan::forward_f32(
                &g,
                slice(xs, xl)?,
                slice(ws, wl)?,
                slice(bs, bl)?,
                self.relu,
            )),
            CpuStorage::F64(_) => {
                let y = kernels::forward(
                    &g,
                    slice(xs, xl)?,
                    slice(ws, wl)?,
                    slice(bs, bl)?,
                    self.relu,
                );
                CpuStorage::F64(y)
            }
            _ => bail!("conv2d: f32 or f64 only"),
        };
        Ok((y, shape))
    }

    fn bwd(&self, x: &Tensor, w: &Tensor, b: &Tensor, y: &Tensor, dy: &Tensor) -> Result<Grads> {
        let work = if x.track_op() { 2.0 } else { 1.0 }; // dW, and dx when asked for
        let g = geom(x.dims(), w.dims())?;
        let _timer = CallTimer::start(g, "backward", work);
        let dy = dy.contiguous()?;
        let t = (x, w, b, y, &dy);
        match x.dtype() {
            DType::F32 => match plan::backward(&g, x.track_op()) {
                Backward::Direct => self.bwd_direct(t),
                Backward::InputByWinograd => self.bwd_split(t),
                Backward::Im2col => self.bwd_typed::<f32>(t),
            },
            DType::F64 => self.bwd_typed::<f64>(t),
            dt => bail!("conv2d: f32 or f64 only, got {dt:?}"),
        }
    }
}

/// With `DEEPSTEREO_CONV_PROFILE=1`, each convolution call prints its shape, time and
/// GFLOP/s to stderr when it ends (a per-layer profile of any command; read once).
struct CallTimer {
    g: Geom,
    what: &'static str,
    /// Products of the call in units of the forward's.
    work: f64,
    start: std::time::Instant,
}

impl CallTimer {
    fn start(g: Geom, what: &'static str, work: f64) -> Option<Self> {
        static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        ON.get_or_init(|| std::env::var("DEEPSTEREO_CONV_PROFILE").is_ok_and(|v| v == "1"))
            .then(|| Self {
                g,
                what,
                work,
                start: std::time::Instant::now(),
            })
    }
}

impl Drop for CallTimer {
    fn drop(&mut self) {
        let g = self.g;
        let s = self.start.elapsed().as_secs_f64();
        let flop = 2.0 * self.work * (g.n * g.p() * g.k() * g.cout) as f64;
        eprintln!(
            "conv {} {}x{}x{}x{} -> {}, {}x{}: {:.2} ms, {:.1} GFLOP/s",
            self.what,
            g.n,
            g.cin,
            g.h,
            g.w,
            g.cout,
            g.kh,
            g.kw,
            s * 1e3,
            flop / s * 1e-9
        );
    }
}
