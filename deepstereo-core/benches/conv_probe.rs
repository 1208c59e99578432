use candle_core::{DType, Device, Module, Result, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use deepstereo_core::conv::Conv2d;
use std::time::Instant;
fn main() -> Result<()> {
    let args: Vec<usize> = std::env::args().skip(1).filter_map(|a| a.parse().ok()).collect();
    let [n, cin, h, w, cout, kh, kw, reps] = args[..8] else { panic!() };
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let conv = Conv2d::new(cin, cout, (kh, kw), VarBuilder::from_varmap(&vm, DType::F32, &dev))?;
    let x = Var::from_tensor(&Tensor::randn(0f32, 1., (n, cin, h, w), &dev)?)?;
    let mut best = [f64::MAX; 3];
    for _ in 0..reps {
        let t = Instant::now();
        let y = conv.forward(x.as_tensor())?;
        let t1 = t.elapsed().as_secs_f64();
        let _g = y.sum_all()?.backward()?;
        let t2 = t.elapsed().as_secs_f64();
        let yy = conv.forward(&x.as_tensor().detach())?;
        let t3 = t.elapsed().as_secs_f64();
        let _g = yy.sum_all()?.backward()?;
        let t4 = t.elapsed().as_secs_f64();
        for (b, v) in best.iter_mut().zip([t1, t2 - t1, t4 - t3]) { *b = b.min(v * 1e3); }
    }
    println!("min ms: fwd {:.1} bwd {:.1} bwd(no dx) {:.1}", best[0], best[1], best[2]);
    Ok(())
}
