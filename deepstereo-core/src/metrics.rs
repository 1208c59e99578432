//! Image quality metrics on colours in [0, 1]: PSNR and SSIM.
//!
//! SSIM follows Wang et al. 2004 as most view-synthesis papers compute it: an 11x11
//! Gaussian window with sigma 1.5, `C1 = (0.01)^2`, `C2 = (0.03)^2`, per channel over the
//! valid window positions, averaged over positions and channels.

use crate::imageio::RgbImage;

/// Floor of the mean squared error in PSNR (caps identical images at 120 dB).
pub const MSE_FLOOR: f64 = 1e-12;
const SSIM_RADIUS: usize = 5;
const SSIM_SIGMA: f64 = 1.5;
const SSIM_C1: f64 = 0.01 * 0.01;
const SSIM_C2: f64 = 0.03 * 0.03;

/// Mean squared error over all pixels and channels (sizes must match).
pub fn mse(a: &RgbImage, b: &RgbImage) -> f64 {
    let n = a.data.len().min(b.data.len()).max(1);
    a.data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / n as f64
}

/// Peak signal-to-noise ratio in dB for colours in [0, 1].
pub fn psnr(a: &RgbImage, b: &RgbImage) -> f64 {
    -10.0 * mse(a, b).max(MSE_FLOOR).log10()
}

/// Structural similarity (mean over channels and window positions).
pub fn ssim(a: &RgbImage, b: &RgbImage) -> f64 {
    let (w, h) = (a.width as usize, a.height as usize);
    let r = SSIM_RADIUS;
    if w <= 2 * r || h <= 2 * r || b.width as usize != w || b.height as usize != h {
        return f64::NAN;
    }
    let k: Vec<f64> = (0..=2 * r)
        .map(|i| (-((i as f64 - r as f64).powi(2)) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp())
        .collect();
    let ks: f64 = k.iter().sum();
    let k: Vec<f64> = k.iter().map(|v| v / ks).collect();
    // Separable blur, valid region only.
    let blur = |img: &[f64]| -> Vec<f64> {
        let (ow, oh) = (w - 2 * r, h - 2 * r);
        let mut tmp = vec![0f64; ow * h];
        for y in 0..h {
            for x in 0..ow {
                tmp[y * ow + x] = (0..=2 * r).map(|i| k[i] * img[y * w + x + i]).sum();
            }
        }
        let mut out = vec![0f64; ow * oh];
        for y in 0..oh {
            for x in 0..ow {
                out[y * ow + x] = (0..=2 * r).map(|i| k[i] * tmp[(y + i) * ow + x]).sum();
            }
        }
        out
    };
    let mut total = 0.0;
    for c in 0..3 {
        let channel = |img: &RgbImage| -> Vec<f64> {
            img.data
                .iter()
                .skip(c)
                .step_by(3)
                .map(|&v| v as f64)
                .collect()
        };
        let (x, y) = (channel(a), channel(b));
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
        let (mx, my, sxx, syy, sxy) = (blur(&x), blur(&y), blur(&xx), blur(&yy), blur(&xy));
        let mut s = 0.0;
        for i in 0..mx.len() {
            let (vx, vy, cxy) = (
                sxx[i] - mx[i] * mx[i],
                syy[i] - my[i] * my[i],
                sxy[i] - mx[i] * my[i],
            );
            s += ((2.0 * mx[i] * my[i] + SSIM_C1) * (2.0 * cxy + SSIM_C2))
                / ((mx[i] * mx[i] + my[i] * my[i] + SSIM_C1) * (vx + vy + SSIM_C2));
        }
        total += s / mx.len() as f64;
    }
    total / 3.0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noise(w: u32, h: u32, seed: u32) -> RgbImage {
        let mut img = RgbImage::new(w, h);
        let mut s = seed;
        for v in img.data.iter_mut() {
            s = s.wrapping_mul(1664525).wrapping_add(1013904223);
            *v = (s >> 8) as f32 / (1u32 << 24) as f32;
        }
        img
    }

    #[test]
    fn identical_images() {
        let a = noise(32, 24, 1);
        assert!((ssim(&a, &a) - 1.0).abs() < 1e-9);
        assert!(psnr(&a, &a) > 100.0);
    }

    #[test]
    fn psnr_of_known_error() {
        let a = noise(16, 16, 2);
        let mut b = a.clone();
        for v in b.data.iter_mut() {
            *v += 0.1;
        }
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-4);
    }

    #[test]
    fn ssim_drops_with_noise() {
        let a = noise(32, 32, 3);
        let b = noise(32, 32, 4);
        assert!(ssim(&a, &b) < 0.1);
    }
}
