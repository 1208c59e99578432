//! Band-limited noise and pattern primitives: value and gradient noise, fractal sums
//! whose octaves finer than a sample's footprint fade to their mean, and the exact box
//! filter of a square wave.

use super::rng::Rng;

/// Noise octaves whose frequency times the footprint exceeds this start fading.
const FADE_START: f32 = 0.25;
/// ... and are gone at this many cycles per sample.
const FADE_END: f32 = 0.6;
/// Frequency ratio between noise octaves.
const LACUNARITY: f32 = 2.0;
/// Filter widths below this are point-sampled.
const MIN_FILTER_WIDTH: f32 = 1e-4;

#[inline]
pub(crate) fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// `floor(x)` as a float and an integer, without a libm call (inputs are far inside the
/// i32 range).
#[inline]
pub(crate) fn floor_i(x: f32) -> (f32, i32) {
    let i = x as i32;
    let i = if (i as f32) > x { i - 1 } else { i };
    (i as f32, i)
}

#[inline]
fn quintic(t: f32) -> f32 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

#[inline]
fn hash2(x: i32, y: i32, seed: u32) -> u32 {
    let mut h = seed ^ (x as u32).wrapping_mul(0x8DA6_B343) ^ (y as u32).wrapping_mul(0xD816_3841);
    h = (h ^ (h >> 15)).wrapping_mul(0x2C1B_3C6D);
    h = (h ^ (h >> 12)).wrapping_mul(0x297A_2D39);
    h ^ (h >> 15)
}

/// Value noise in [-1, 1].
#[inline]
fn value_noise(x: f32, y: f32, seed: u32) -> f32 {
    let ((fx, ix), (fy, iy)) = (floor_i(x), floor_i(y));
    let (tx, ty) = (quintic(x - fx), quintic(y - fy));
    let l =
        |dx: i32, dy: i32| (hash2(ix + dx, iy + dy, seed) >> 8) as f32 * (2.0 / 16_777_216.0) - 1.0;
    let a = l(0, 0) + (l(1, 0) - l(0, 0)) * tx;
    let b = l(0, 1) + (l(1, 1) - l(0, 1)) * tx;
    a + (b - a) * ty
}

/// Gradient (Perlin) noise, roughly in [-1, 1].
#[inline]
fn gradient_noise(x: f32, y: f32, seed: u32) -> f32 {
    const D: f32 = std::f32::consts::FRAC_1_SQRT_2;
    const DIRS: [[f32; 2]; 8] = [
        [1.0, 0.0],
        [-1.0, 0.0],
        [0.0, 1.0],
        [0.0, -1.0],
        [D, D],
        [-D, D],
        [D, -D],
        [-D, -D],
    ];
    let ((fx, ix), (fy, iy)) = (floor_i(x), floor_i(y));
    let (rx, ry) = (x - fx, y - fy);
    let g = |dx: i32, dy: i32| {
        let d = DIRS[(hash2(ix + dx, iy + dy, seed) >> 29) as usize];
        d[0] * (rx - dx as f32) + d[1] * (ry - dy as f32)
    };
    let (tx, ty) = (quintic(rx), quintic(ry));
    let a = g(0, 0) + (g(1, 0) - g(0, 0)) * tx;
    let b = g(0, 1) + (g(1, 1) - g(0, 1)) * tx;
    1.4 * (a + (b - a) * ty)
}

/// Fractal sum of noise octaves, mean 0, roughly in [-1, 1].
#[derive(Clone, Debug)]
pub(crate) struct Fbm {
    freq: f32,
    octaves: u32,
    gain: f32,
    gradient: bool,
    seed: u32,
}

impl Fbm {
    pub fn random(rng: &mut Rng, freq: (f64, f64), octaves: (usize, usize)) -> Self {
        Self {
            freq: rng.log_range(freq.0, freq.1) as f32,
            octaves: rng.int_in(octaves.0, octaves.1) as u32,
            gain: rng.range(0.4, 0.65) as f32,
            gradient: rng.chance(0.5),
            seed: rng.seed32(),
        }
    }

    /// The sum at `(x, y)`, octaves finer than the footprint `fp` faded out.
    pub fn eval(&self, x: f32, y: f32, fp: f32) -> f32 {
        let (mut f, mut amp, mut sum, mut norm) = (self.freq, 1.0f32, 0.0f32, 0.0f32);
        for o in 0..self.octaves {
            let w = 1.0 - smoothstep(FADE_START, FADE_END, f * fp);
            if w > 0.0 {
                let (ox, oy) = (x * f + 17.31 * o as f32, y * f - 9.73 * o as f32);
                let seed = self.seed.wrapping_add(o.wrapping_mul(0x9E37_79B9));
                let n = if self.gradient {
                    gradient_noise(ox, oy, seed)
                } else {
                    value_noise(ox, oy, seed)
                };
                sum += amp * w * n;
            }
            norm += amp;
            amp *= self.gain;
            f *= LACUNARITY;
        }
        if norm > 0.0 {
            sum / norm
        } else {
            0.0
        }
    }
}

/// Fraction of `[x - w/2, x + w/2]` where the square wave (1 on `[k, k + duty)`) is 1:
/// the exact box filter of the wave.
#[inline]
pub(crate) fn box_square(x: f32, w: f32, duty: f32) -> f32 {
    if w < MIN_FILTER_WIDTH {
        return if x - floor_i(x).0 < duty { 1.0 } else { 0.0 };
    }
    let (a, b) = (x - 0.5 * w, x + 0.5 * w);
    let (fa, fb) = (floor_i(a).0, floor_i(b).0);
    (((fb - fa) * duty + (b - fb).min(duty) - (a - fa).min(duty)) / w).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn synth_box_square_averages_to_duty() {
        for &duty in &[0.3f32, 0.5, 0.7] {
            assert_eq!(box_square(0.1, 0.0, duty), 1.0);
            assert!((box_square(3.37, 10.0, duty) - duty).abs() < 1e-3);
            let s = box_square(0.2, 0.2, duty);
            assert!((0.0..=1.0).contains(&s));
        }
        for x in [-3.7f32, -0.5, 0.0, 0.99, 1.0, 2.5] {
            assert_eq!(floor_i(x).0, x.floor());
        }
    }
}
