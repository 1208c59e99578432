//! Pictures for people: colour-mapped depth and greyscale maps, images side by side with
//! titles drawn over them.

pub mod font;

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

/// Draws `text` in `colour` with its top-left corner at `(x, y)`, each font pixel a
/// `scale` x `scale` square ([`font`]); what falls outside the image is left out.
pub fn draw_text(img: &mut RgbImage, text: &str, (x, y): (u32, u32), scale: u32, colour: [f32; 3]) {
    let (gw, gh) = font::GLYPH;
    for (i, c) in text.chars().enumerate() {
        let Some(rows) = font::glyph(c) else {
            continue;
        };
        let x0 = x + i as u32 * (gw + 1) * scale;
        for (r, bits) in rows.iter().enumerate().take(gh as usize) {
            for col in 0..gw {
                if bits >> (gw - 1 - col) & 1 == 0 {
                    continue;
                }
                for dy in 0..scale {
                    for dx in 0..scale {
                        let (px, py) = (x0 + col * scale + dx, y + r as u32 * scale + dy);
                        if px < img.width && py < img.height {
                            let p = (py * img.width + px) as usize * 3;
                            img.data[p..p + 3].copy_from_slice(&colour);
                        }
                    }
                }
            }
        }
    }
}

/// The width `text` takes at `scale`.
pub fn text_width(text: &str, scale: u32) -> u32 {
    let n = text.chars().count() as u32;
    (n * (font::GLYPH.0 + 1)).saturating_sub(1) * scale
}

/// Images side by side under titles: each under a black strip holding its title in white,
/// centred, all at one size (twice the font's when every title fits its image, else the
/// font's own, cut at the edges when even that is too wide), separated by `gap` pixels.
pub fn titled_side_by_side(panels: &[(&RgbImage, &str)], gap: u32) -> RgbImage {
    let fits = |scale| {
        panels
            .iter()
            .all(|(i, t)| text_width(t, scale) + 4 <= i.width)
    };
    let scale = if fits(2) { 2 } else { 1 };
    let titled: Vec<RgbImage> = panels.iter().map(|(i, t)| titled(i, t, scale)).collect();
    side_by_side(&titled.iter().collect::<Vec<_>>(), gap)
}

/// `img` under a black strip holding `title` in white, centred, at `scale`.
pub fn titled(img: &RgbImage, title: &str, scale: u32) -> RgbImage {
    let strip = font::GLYPH.1 * scale + 2 * TITLE_PAD;
    let mut out = RgbImage::new(img.width, img.height + strip);
    let n = img.data.len();
    out.data[(strip * img.width * 3) as usize..][..n].copy_from_slice(&img.data);
    let x = img.width.saturating_sub(text_width(title, scale)) / 2;
    draw_text(&mut out, title, (x, TITLE_PAD), scale, [1.0, 1.0, 1.0]);
    out
}

/// Space above and below a title, in pixels.
const TITLE_PAD: u32 = 4;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_title_is_drawn_in_a_strip_above_the_picture() {
        let mut img = RgbImage::new(80, 20);
        img.data.iter_mut().for_each(|v| *v = 0.5);
        let t = titled(&img, "DEPTH", 2);
        let strip = 7 * 2 + 2 * TITLE_PAD;
        assert_eq!((t.width, t.height), (80, 20 + strip));
        // The picture is below the strip, unchanged.
        assert_eq!(&t.data[(strip * 80 * 3) as usize..], &img.data[..]);
        // White pixels in the strip, centred: as many left of the middle as right of it.
        let white = |x: u32, y: u32| t.pixel(x, y) == [1.0; 3];
        let cols: Vec<u32> = (0..80)
            .filter(|&x| (0..strip).any(|y| white(x, y)))
            .collect();
        assert!(!cols.is_empty(), "no text drawn");
        let (l, r) = (cols[0], 79 - cols[cols.len() - 1]);
        assert!(l.abs_diff(r) <= 1, "not centred: {l} left, {r} right");
        // "D" starts with its full-height stem: 7 font pixels at scale 2.
        assert_eq!((0..strip).filter(|&y| white(cols[0], y)).count(), 14);
        // Different titles draw different pixels; unknown characters draw nothing.
        assert_ne!(titled(&img, "TRUTH", 2).data, t.data);
        assert_eq!(
            titled(&img, "~~~", 2).data[..(strip * 80 * 3) as usize],
            vec![0.0; (strip * 80 * 3) as usize][..]
        );
    }

    #[test]
    fn titles_side_by_side_share_one_size() {
        let img = RgbImage::new(40, 10);
        // "A LONG TITLE" does not fit 40 px at twice the size: every title is drawn at 1x.
        let row = titled_side_by_side(&[(&img, "AB"), (&img, "A LONG TITLE")], 2);
        assert_eq!((row.width, row.height), (82, 10 + 7 + 2 * TITLE_PAD));
        let row = titled_side_by_side(&[(&img, "AB"), (&img, "CD")], 2);
        assert_eq!(row.height, 10 + 14 + 2 * TITLE_PAD);
    }
}
