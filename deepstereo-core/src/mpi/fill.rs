//! Rays that no MPI plane covers (a camera turned or moved beyond the MPI's image sees
//! past its edges) filled from the covered pixels around them, as a GPU does with a mipmap: the
//! image premultiplied by its coverage (1 covered, 0 not) is halved level by level, each
//! pixel the mean of its (up to) 2x2 children; a hole takes `P / A` of the finest level
//! whose premultiplied colour `P` and coverage `A`, sampled bilinearly at the hole's
//! centre (pixel centres at `i + 0.5`: level `L` samples at `(x + 0.5) / 2^L - 0.5`),
//! has `A > MIN_COVERAGE`. The viewer does the same with `generateMipmap` and
//! `textureLod`.

use crate::imageio::RgbImage;

/// The least coverage a level must hold at a hole to fill it (half a step of 8 bits, as
/// the viewer's RGBA8 mipmap holds it).
pub const MIN_COVERAGE: f32 = 0.5 / 255.0;

/// One level: premultiplied colour and coverage `[H, W, 4]`.
struct Level {
    w: usize,
    h: usize,
    rgba: Vec<f32>,
}

impl Level {
    /// The level above: each pixel the mean of its children (up to 2x2: the last row or
    /// column of an odd size has fewer).
    fn coarser(&self) -> Level {
        let (w, h) = (self.w.div_ceil(2), self.h.div_ceil(2));
        let mut rgba = vec![0f32; w * h * 4];
        for y in 0..h {
            for x in 0..w {
                let (mut c, mut n) = ([0f32; 4], 0f32);
                for (cx, cy) in [
                    (2 * x, 2 * y),
                    (2 * x + 1, 2 * y),
                    (2 * x, 2 * y + 1),
                    (2 * x + 1, 2 * y + 1),
                ] {
                    if cx < self.w && cy < self.h {
                        let p = (cy * self.w + cx) * 4;
                        c.iter_mut()
                            .zip(&self.rgba[p..p + 4])
                            .for_each(|(a, b)| *a += b);
                        n += 1.0;
                    }
                }
                let p = (y * w + x) * 4;
                rgba[p..p + 4]
                    .iter_mut()
                    .zip(c)
                    .for_each(|(o, v)| *o = v / n);
            }
        }
        Level { w, h, rgba }
    }

    /// Bilinear sample at `(u, v)` in this level's pixels (edges clamped).
    fn sample(&self, u: f32, v: f32) -> [f32; 4] {
        let (x0, y0) = (u.floor(), v.floor());
        let (ax, ay) = (u - x0, v - y0);
        let at = |x: f32, y: f32| {
            let x = (x as isize).clamp(0, self.w as isize - 1) as usize;
            let y = (y as isize).clamp(0, self.h as isize - 1) as usize;
            &self.rgba[(y * self.w + x) * 4..][..4]
        };
        let (a, b, c, d) = (
            at(x0, y0),
            at(x0 + 1.0, y0),
            at(x0, y0 + 1.0),
            at(x0 + 1.0, y0 + 1.0),
        );
        let mut out = [0f32; 4];
        for k in 0..4 {
            out[k] =
                (a[k] * (1.0 - ax) + b[k] * ax) * (1.0 - ay) + (c[k] * (1.0 - ax) + d[k] * ax) * ay;
        }
        out
    }
}

/// Fills the pixels of `img` where `covered` is false from the covered ones (see the
/// module); unchanged when every pixel or none is covered (or `covered` is not one flag
/// per pixel).
pub fn fill_holes(img: &mut RgbImage, covered: &[bool]) {
    let (w, h) = (img.width as usize, img.height as usize);
    if covered.len() != w * h || covered.iter().all(|&c| c) || !covered.iter().any(|&c| c) {
        return;
    }
    let mut rgba = vec![0f32; w * h * 4];
    for (p, &c) in covered.iter().enumerate() {
        if c {
            rgba[p * 4..p * 4 + 3].copy_from_slice(&img.data[p * 3..p * 3 + 3]);
            rgba[p * 4 + 3] = 1.0;
        }
    }
    let mut levels = vec![Level { w, h, rgba }];
    while levels.last().is_some_and(|l| l.w > 1 || l.h > 1) {
        let next = levels.last().map(Level::coarser);
        levels.extend(next);
    }
    for (p, _) in covered.iter().enumerate().filter(|(_, &c)| !c) {
        let (x, y) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
        for (l, level) in levels.iter().enumerate().skip(1) {
            let s = (1u64 << l) as f32;
            let v = level.sample(x / s - 0.5, y / s - 0.5);
            if v[3] > MIN_COVERAGE {
                for k in 0..3 {
                    img.data[p * 3 + k] = v[k] / v[3];
                }
                break;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn covered_pixels_stay_and_holes_take_their_surroundings() {
        let (w, h) = (9usize, 7usize);
        let mut img = RgbImage::new(w as u32, h as u32);
        let mut covered = vec![true; w * h];
        for (p, cov) in covered.iter_mut().enumerate() {
            let x = p % w;
            // Left half red, right half blue; a hole down the middle and in a corner.
            let c = if x < 4 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 0.0, 1.0]
            };
            img.data[p * 3..p * 3 + 3].copy_from_slice(&c);
            if x == 4 || (x >= 7 && p / w >= 5) {
                *cov = false;
                img.data[p * 3..p * 3 + 3].copy_from_slice(&[0.0; 3]);
            }
        }
        let before = img.clone();
        fill_holes(&mut img, &covered);
        for (p, &cov) in covered.iter().enumerate() {
            let px = &img.data[p * 3..p * 3 + 3];
            if cov {
                assert_eq!(
                    px,
                    &before.data[p * 3..p * 3 + 3],
                    "covered pixel {p} changed"
                );
            } else if p % w >= 7 {
                // Deep in the blue half: blue.
                assert!(px[2] > 0.9 && px[0] < 0.1, "corner hole {p}: {px:?}");
            } else {
                // Between red and blue: a mix of both, nothing else.
                assert!(
                    px[0] > 0.2 && px[2] > 0.2 && px[1] == 0.0,
                    "seam hole {p}: {px:?}"
                );
                assert!((px[0] + px[2] - 1.0).abs() < 1e-5, "seam hole {p}: {px:?}");
            }
        }
    }

    #[test]
    fn nothing_or_everything_covered_leaves_the_image() {
        let mut img = RgbImage::new(5, 4);
        img.data
            .iter_mut()
            .enumerate()
            .for_each(|(i, v)| *v = i as f32 / 60.0);
        let before = img.clone();
        fill_holes(&mut img, &[false; 20]);
        assert_eq!(img.data, before.data);
        fill_holes(&mut img, &[true; 20]);
        assert_eq!(img.data, before.data);
    }
}
