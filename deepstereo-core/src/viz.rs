//! Pictures for people: colour-mapped depth and greyscale maps.

use crate::imageio::RgbImage;

/// Control points of a perceptually ordered colour map (dark blue -> yellow, as viridis).
const COLOURS: [[f32; 3]; 6] = [
    [0.267, 0.005, 0.329],
    [0.253, 0.265, 0.530],
    [0.164, 0.471, 0.558],
    [0.135, 0.659, 0.518],
    [0.478, 0.821, 0.320],
    [0.993, 0.906, 0.144],
];

/// Maps `t` in [0, 1] to a colour (non-finite values map to black).
pub fn colour_map(t: f32) -> [f32; 3] {
    if !t.is_finite() {
        return [0.0; 3];
    }
    let x = t.clamp(0.0, 1.0) * (COLOURS.len() - 1) as f32;
    let i = (x.floor() as usize).min(COLOURS.len() - 2);
    let f = x - i as f32;
    let (a, b) = (COLOURS[i], COLOURS[i + 1]);
    [
        a[0] + f * (b[0] - a[0]),
        a[1] + f * (b[1] - a[1]),
        a[2] + f * (b[2] - a[2]),
    ]
}

/// Depth map `[H, W]` as a picture: inverse depth between `1/far` (dark) and `1/near`
/// (bright), so near surfaces stand out; `far` may be infinite.
pub fn depth_image(depth: &[f32], width: u32, height: u32, near: f64, far: f64) -> RgbImage {
    let (lo, hi) = (1.0 / far, 1.0 / near);
    let mut img = RgbImage::new(width, height);
    for (p, &z) in depth.iter().enumerate().take((width * height) as usize) {
        let t = if z > 0.0 {
            ((1.0 / z as f64 - lo) / (hi - lo)) as f32
        } else {
            f32::NAN
        };
        img.data[p * 3..p * 3 + 3].copy_from_slice(&colour_map(t));
    }
    img
}

/// A `[H, W]` map of values in [0, 1] as a grey picture.
pub fn grey_image(values: &[f32], width: u32, height: u32) -> RgbImage {
    let mut img = RgbImage::new(width, height);
    for (p, &v) in values.iter().enumerate().take((width * height) as usize) {
        let g = if v.is_finite() {
            v.clamp(0.0, 1.0)
        } else {
            0.0
        };
        img.data[p * 3..p * 3 + 3].copy_from_slice(&[g, g, g]);
    }
    img
}

/// Images side by side (heights may differ; the canvas is as tall as the tallest),
/// separated by `gap` black pixels.
pub fn side_by_side(images: &[&RgbImage], gap: u32) -> RgbImage {
    let w: u32 =
        images.iter().map(|i| i.width).sum::<u32>() + gap * images.len().saturating_sub(1) as u32;
    let h = images.iter().map(|i| i.height).max().unwrap_or(0);
    let mut out = RgbImage::new(w, h);
    let mut x0 = 0u32;
    for img in images {
        for y in 0..img.height {
            let src = (y * img.width * 3) as usize;
            let dst = ((y * w + x0) * 3) as usize;
            let n = (img.width * 3) as usize;
            out.data[dst..dst + n].copy_from_slice(&img.data[src..src + n]);
        }
        x0 += img.width + gap;
    }
    out
}
