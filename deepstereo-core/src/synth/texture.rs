//! Procedural textures (multi-octave value/gradient noise, stripes, checks, gradients,
//! smooth patches) with natural random palettes, and crops of user photos.
//!
//! A texture is evaluated at continuous coordinates `(u, v)` (one texture unit spans a
//! rectangle's longer side) together with the footprint `fp` of the sample in texture
//! units. Detail finer than the footprint is faded to its mean (noise octaves) or box
//! filtered exactly (stripes, checks), so the supersampled renderer does not alias.

use super::noise::{box_square, Fbm};
use super::rng::Rng;
use crate::imageio::RgbImage;

/// Most colours in a palette.
const MAX_PALETTE: usize = 4;
/// Scale of fBm (roughly in [-1, 1]) to palette position offsets.
const NOISE_CONTRAST: f32 = 1.8;

/// What a texture is for; each draws its patterns with different odds and scales.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Role {
    Panel,
    Thin,
    Backdrop,
}

/// A few related colours with natural statistics (muted, varied brightness).
#[derive(Clone, Debug)]
pub(crate) struct Palette {
    colours: [[f32; 3]; MAX_PALETTE],
    len: usize,
}

impl Palette {
    pub fn random(rng: &mut Rng, n: usize) -> Self {
        let len = n.clamp(2, MAX_PALETTE);
        let scheme = rng.weighted(&[0.45, 0.2, 0.35]);
        let h0 = rng.unit();
        let (v_lo, v_hi) = (rng.range(0.08, 0.4), rng.range(0.55, 0.95));
        let reverse = rng.chance(0.5);
        let mut colours = [[0.0f32; 3]; MAX_PALETTE];
        for (i, c) in colours.iter_mut().take(len).enumerate() {
            let (h, s) = match scheme {
                0 => (h0 + rng.sym(0.07), rng.range(0.1, 0.55)),
                1 => (
                    h0 + 0.5 * (i % 2) as f64 + rng.sym(0.04),
                    rng.range(0.05, 0.4),
                ),
                _ => (0.1 * h0 + 0.03 + rng.sym(0.04), rng.range(0.0, 0.25)),
            };
            let k = i as f64 / (len - 1) as f64;
            let k = if reverse { 1.0 - k } else { k };
            let v = v_lo + (v_hi - v_lo) * k + rng.sym(0.05);
            *c = hsv(h, s, v.clamp(0.02, 0.98));
        }
        Self { colours, len }
    }

    /// Piecewise-linear colour ramp through the palette, `s` clamped to [0, 1].
    #[inline]
    pub fn at(&self, s: f32) -> [f32; 3] {
        let x = s.clamp(0.0, 1.0) * (self.len - 1) as f32;
        let i = (x as usize).min(self.len - 2);
        mix(self.colours[i], self.colours[i + 1], x - i as f32)
    }

    fn first(&self) -> [f32; 3] {
        self.colours[0]
    }

    fn last(&self) -> [f32; 3] {
        self.colours[self.len - 1]
    }
}

/// HSV (all in [0, 1], hue wrapping) to RGB.
fn hsv(h: f64, s: f64, v: f64) -> [f32; 3] {
    let h6 = h.rem_euclid(1.0) * 6.0;
    let sector = h6.floor();
    let f = h6 - sector;
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    let (r, g, b) = match sector as u32 {
        0 => (v, t, p),
        1 => (q, v, p),
        2 => (p, v, t),
        3 => (p, q, v),
        4 => (t, p, v),
        _ => (v, p, q),
    };
    [r as f32, g as f32, b as f32]
}

#[inline]
pub(crate) fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// The spatial pattern of a texture.
#[derive(Clone, Debug)]
pub(crate) enum Pattern {
    Noise(Fbm),
    Stripes {
        freq: f32,
        duty: f32,
        warp: Fbm,
        warp_amount: f32,
    },
    Checks {
        fu: f32,
        fv: f32,
    },
    Gradient,
    Smooth,
    /// A square crop of `photos[index]`: corner `(x0, y0)` and side `size` in pixels,
    /// mirrored outside [0, 1].
    Photo {
        index: usize,
        x0: f32,
        y0: f32,
        size: f32,
        flip: bool,
    },
}

/// A texture: a pattern coloured by a palette, rotated and shifted in its plane, with a
/// fine multiplicative noise "detail" on top.
#[derive(Clone, Debug)]
pub(crate) struct Texture {
    pattern: Pattern,
    palette: Palette,
    rot: [f32; 2],
    offset: [f32; 2],
    detail: Fbm,
    detail_amount: f32,
}

impl Texture {
    /// A random procedural texture for a surface of the given role.
    pub fn procedural(rng: &mut Rng, role: Role) -> Self {
        let weights: &[f64] = match role {
            Role::Panel => &[0.38, 0.17, 0.15, 0.14, 0.16],
            Role::Thin => &[0.1, 0.3, 0.0, 0.3, 0.3],
            Role::Backdrop => &[0.75, 0.0, 0.0, 0.15, 0.1],
        };
        let colours = rng.int_in(2, MAX_PALETTE);
        let palette = Palette::random(rng, colours);
        let pattern = match rng.weighted(weights) {
            0 => match role {
                Role::Backdrop => Pattern::Noise(Fbm::random(rng, (1.0, 4.0), (4, 7))),
                _ => Pattern::Noise(Fbm::random(rng, (1.5, 8.0), (2, 6))),
            },
            1 => Pattern::Stripes {
                freq: rng.log_range(2.0, 12.0) as f32,
                duty: rng.range(0.3, 0.7) as f32,
                warp: Fbm::random(rng, (0.5, 2.0), (1, 3)),
                warp_amount: rng.range(0.0, 0.4) as f32,
            },
            2 => {
                let fu = rng.log_range(1.5, 8.0);
                Pattern::Checks {
                    fu: fu as f32,
                    fv: (fu * rng.range(0.7, 1.4)) as f32,
                }
            }
            3 => Pattern::Gradient,
            _ => Pattern::Smooth,
        };
        let detail_amount = match pattern {
            Pattern::Smooth => rng.range(0.0, 0.04),
            _ => rng.range(0.02, 0.15),
        } as f32;
        Self::finish(rng, pattern, palette, detail_amount)
    }

    /// A random crop of about `crop_px` pixels of one of `photos` (non-empty).
    pub fn photo(rng: &mut Rng, photos: &[RgbImage], crop_px: f64) -> Self {
        let index = rng.below(photos.len());
        let (w, h) = photos
            .get(index)
            .map_or((1.0, 1.0), |p| (p.width as f64, p.height as f64));
        let size = crop_px.clamp(1.0, w.min(h));
        let pattern = Pattern::Photo {
            index,
            x0: rng.range(0.0, w - size) as f32,
            y0: rng.range(0.0, h - size) as f32,
            size: size as f32,
            flip: rng.chance(0.5),
        };
        let palette = Palette::random(rng, 2);
        Self::finish(rng, pattern, palette, 0.0)
    }

    fn finish(rng: &mut Rng, pattern: Pattern, palette: Palette, detail_amount: f32) -> Self {
        let a = rng.range(0.0, std::f64::consts::TAU);
        Self {
            pattern,
            palette,
            rot: [a.cos() as f32, a.sin() as f32],
            offset: [rng.sym(10.0) as f32, rng.sym(10.0) as f32],
            detail: Fbm::random(rng, (8.0, 40.0), (2, 3)),
            detail_amount,
        }
    }

    /// Whether the texture filters itself by the footprint (procedural patterns do; photo
    /// crops are point-sampled and need supersampling).
    pub fn prefiltered(&self) -> bool {
        !matches!(self.pattern, Pattern::Photo { .. })
    }

    /// Colour at texture coordinates `(u, v)` for a sample of footprint `fp`.
    pub fn eval(&self, u: f32, v: f32, fp: f32, photos: &[RgbImage]) -> [f32; 3] {
        let (cu, cv) = (u - 0.5, v - 0.5);
        let x = self.rot[0] * cu - self.rot[1] * cv + self.offset[0];
        let y = self.rot[1] * cu + self.rot[0] * cv + self.offset[1];
        let p = &self.palette;
        let base = match &self.pattern {
            Pattern::Noise(f) => p.at(0.5 + 0.5 * NOISE_CONTRAST * f.eval(x, y, fp)),
            Pattern::Stripes {
                freq,
                duty,
                warp,
                warp_amount,
            } => {
                let phase = x * freq + warp_amount * warp.eval(x, y, fp);
                mix(p.first(), p.last(), box_square(phase, fp * freq, *duty))
            }
            Pattern::Checks { fu, fv } => {
                let a = box_square(x * fu, fp * fu, 0.5);
                let b = box_square(y * fv, fp * fv, 0.5);
                mix(p.first(), p.last(), a * b + (1.0 - a) * (1.0 - b))
            }
            Pattern::Gradient => p.at(cu * self.rot[0] + cv * self.rot[1] + 0.5),
            Pattern::Smooth => p.at(0.5),
            Pattern::Photo {
                index,
                x0,
                y0,
                size,
                flip,
            } => {
                let uu = if *flip { 1.0 - u } else { u };
                match photos.get(*index) {
                    Some(img) => sample_photo(img, x0 + mirror(uu) * size, y0 + mirror(v) * size),
                    None => p.at(0.5),
                }
            }
        };
        if self.detail_amount > 0.0 {
            let m = 1.0 + self.detail_amount * self.detail.eval(x, y, fp);
            [base[0] * m, base[1] * m, base[2] * m]
        } else {
            base
        }
    }
}

/// Reflects `t` into [0, 1] (mirrored repeat).
#[inline]
fn mirror(t: f32) -> f32 {
    let r = t.rem_euclid(2.0);
    if r > 1.0 {
        2.0 - r
    } else {
        r
    }
}

/// Bilinear sample at pixel coordinates (centres at `i + 0.5`), clamped to the edges.
fn sample_photo(img: &RgbImage, x: f32, y: f32) -> [f32; 3] {
    let (w, h) = (img.width as usize, img.height as usize);
    if w == 0 || h == 0 || img.data.len() < w * h * 3 {
        return [0.5; 3];
    }
    let sx = (x - 0.5).clamp(0.0, (w - 1) as f32);
    let sy = (y - 0.5).clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (sx as usize, sy as usize); // sx, sy >= 0: truncation is floor
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (ax, ay) = (sx - x0 as f32, sy - y0 as f32);
    let px = |xx: usize, yy: usize| {
        let i = (yy * w + xx) * 3;
        [img.data[i], img.data[i + 1], img.data[i + 2]]
    };
    let top = mix(px(x0, y0), px(x1, y0), ax);
    let bottom = mix(px(x0, y1), px(x1, y1), ax);
    mix(top, bottom, ay)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn synth_textures_stay_in_range() {
        let mut rng = Rng::new(3);
        for role in [Role::Panel, Role::Thin, Role::Backdrop] {
            for _ in 0..50 {
                let t = Texture::procedural(&mut rng, role);
                for k in 0..50 {
                    let c = t.eval(k as f32 * 0.37 - 3.0, k as f32 * 0.11, 0.01 * k as f32, &[]);
                    assert!(
                        c.iter().all(|v| v.is_finite() && *v >= 0.0 && *v < 1.3),
                        "{c:?}"
                    );
                }
            }
        }
    }
}
