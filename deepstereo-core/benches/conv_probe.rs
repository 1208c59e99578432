use candle_core::{DType, Device, Module, Result, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use deepstereo_core::conv::Conv2d;
use std::time::Instant;
fn cpu_ns() -> f64 {
    let mut t = 0.0;
    for e in std::fs::read_dir("/proc/self/task").unwrap() {
        let p = e.unwrap().path().join("schedstat");
        if let Ok(s) = std::fs::read_to_string(p) { t += s.split_whitespace().next().unwrap().parse::<f64>().unwrap(); }
    }
    t
}
// args: n cin h w cout kh kw rounds ; env VARIANTS="CB:MC,CB:MC"
fn main() -> Result<()> {
    let args: Vec<usize> = std::env::args().skip(1).filter_map(|a| a.parse().ok()).collect();
    let [n, cin, h, w, cout, kh, kw, rounds] = args[..8] else { panic!() };
    let variants: Vec<String> = std::env::var("VARIANTS").unwrap_or("393216:128".into()).split(',').map(String::from).collect();
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let conv = Conv2d::new(cin, cout, (kh, kw), VarBuilder::from_varmap(&vm, DType::F32, &dev))?;
    let x = Var::from_tensor(&Tensor::randn(0f32, 1., (n, cin, h, w), &dev)?)?;
    let mut best = vec![[f64::MAX; 3]; variants.len()];
    for _ in 0..rounds {
        for (vi, v) in variants.iter().enumerate() {
            let mut it = v.split(':');
            std::env::set_var("CONV_CB", it.next().unwrap());
            std::env::set_var("CONV_MC", it.next().unwrap_or("128"));
            if let Some(x) = it.next() { std::env::set_var("CONV_ALT", x); } else { std::env::remove_var("CONV_ALT"); }
            let c = || cpu_ns() * 1e-9 / 2.0;
            let t0 = c();
            let y = conv.forward(x.as_tensor())?;
            let t1 = c() - t0;
            let _g = y.sum_all()?.backward()?;
            let t2 = c() - t0;
            let yy = conv.forward(&x.as_tensor().detach())?;
            let t3 = c() - t0;
            let _g = yy.sum_all()?.backward()?;
            let t4 = c() - t0;
            for (b, v) in best[vi].iter_mut().zip([t1, t2 - t1, t4 - t3]) { *b = b.min(v * 1e3); }
        }
    }
    for (v, b) in variants.iter().zip(&best) {
        println!("{v:>16}: min cpu-ms/2 fwd {:7.1} bwd {:7.1} bwd(no dx) {:7.1}", b[0], b[1], b[2]);
    }
    Ok(())
}
