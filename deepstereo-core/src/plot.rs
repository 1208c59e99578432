//! Minimal raster line and scatter plots as PNG-ready images (no font or plotting
//! dependency): axes with tick labels in a built-in 5x7 bitmap font, series as lines or
//! markers, a legend.

use crate::imageio::RgbImage;

/// 5x7 glyphs, one byte per row (low 5 bits, MSB = leftmost column).
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        '0' => [14, 17, 19, 21, 25, 17, 14],
        '1' => [4, 12, 4, 4, 4, 4, 14],
        '2' => [14, 17, 1, 2, 4, 8, 31],
        '3' => [31, 2, 4, 2, 1, 17, 14],
        '4' => [2, 6, 10, 18, 31, 2, 2],
        '5' => [31, 16, 30, 1, 1, 17, 14],
        '6' => [6, 8, 16, 30, 17, 17, 14],
        '7' => [31, 1, 2, 4, 8, 8, 8],
        '8' => [14, 17, 17, 14, 17, 17, 14],
        '9' => [14, 17, 17, 15, 1, 2, 12],
        '.' => [0, 0, 0, 0, 0, 12, 12],
        '-' => [0, 0, 0, 31, 0, 0, 0],
        '+' => [0, 4, 4, 31, 4, 4, 0],
        '/' => [1, 1, 2, 4, 8, 16, 16],
        '(' => [2, 4, 8, 8, 8, 4, 2],
        ')' => [8, 4, 2, 2, 2, 4, 8],
        ':' => [0, 12, 12, 0, 12, 12, 0],
        '=' => [0, 0, 31, 0, 31, 0, 0],
        '_' => [0, 0, 0, 0, 0, 0, 31],
        'A' => [14, 17, 17, 31, 17, 17, 17],
        'B' => [30, 17, 17, 30, 17, 17, 30],
        'C' => [14, 17, 16, 16, 16, 17, 14],
        'D' => [28, 18, 17, 17, 17, 18, 28],
        'E' => [31, 16, 16, 30, 16, 16, 31],
        'F' => [31, 16, 16, 30, 16, 16, 16],
        'G' => [14, 17, 16, 23, 17, 17, 15],
        'H' => [17, 17, 17, 31, 17, 17, 17],
        'I' => [14, 4, 4, 4, 4, 4, 14],
        'J' => [7, 2, 2, 2, 2, 18, 12],
        'K' => [17, 18, 20, 24, 20, 18, 17],
        'L' => [16, 16, 16, 16, 16, 16, 31],
        'M' => [17, 27, 21, 21, 17, 17, 17],
        'N' => [17, 17, 25, 21, 19, 17, 17],
        'O' => [14, 17, 17, 17, 17, 17, 14],
        'P' => [30, 17, 17, 30, 16, 16, 16],
        'Q' => [14, 17, 17, 17, 21, 18, 13],
        'R' => [30, 17, 17, 30, 20, 18, 17],
        'S' => [15, 16, 16, 14, 1, 1, 30],
        'T' => [31, 4, 4, 4, 4, 4, 4],
        'U' => [17, 17, 17, 17, 17, 17, 14],
        'V' => [17, 17, 17, 17, 17, 10, 4],
        'W' => [17, 17, 17, 21, 21, 21, 10],
        'X' => [17, 17, 10, 4, 10, 17, 17],
        'Y' => [17, 17, 10, 4, 4, 4, 4],
        'Z' => [31, 1, 2, 4, 8, 16, 31],
        _ => [0; 7],
    }
}

/// A series to draw.
pub struct Series {
    pub label: String,
    pub colour: [f32; 3],
    pub points: Vec<(f64, f64)>,
    /// Join points with lines (else markers only).
    pub line: bool,
    /// Marker half-size in pixels (0: none).
    pub marker: i32,
    /// A short text drawn next to each point (empty: none; else one per point).
    pub labels: Vec<String>,
}

const W: i32 = 900;
const H: i32 = 480;
const LEFT: i32 = 70;
/// The legend sits right of the plot area, so that it never hides a point.
const RIGHT: i32 = 220;
const TOP: i32 = 30;
const BOTTOM: i32 = 50;

fn put(img: &mut RgbImage, x: i32, y: i32, c: [f32; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width && (y as u32) < img.height {
        let i = ((y as u32 * img.width + x as u32) * 3) as usize;
        img.data[i..i + 3].copy_from_slice(&c);
    }
}

/// Draws `text` with its top-left corner at `(x, y)`.
pub fn text(img: &mut RgbImage, x: i32, y: i32, s: &str, c: [f32; 3]) {
    for (k, ch) in s.chars().enumerate() {
        for (r, row) in glyph(ch).iter().enumerate() {
            for col in 0..5 {
                if row & (16 >> col) != 0 {
                    put(img, x + k as i32 * 6 + col, y + r as i32, c);
                }
            }
        }
    }
}

fn line(img: &mut RgbImage, (x0, y0): (i32, i32), (x1, y1): (i32, i32), c: [f32; 3]) {
    let n = (x1 - x0).abs().max((y1 - y0).abs()).max(1);
    for i in 0..=n {
        let t = i as f64 / n as f64;
        put(
            img,
            x0 + ((x1 - x0) as f64 * t).round() as i32,
            y0 + ((y1 - y0) as f64 * t).round() as i32,
            c,
        );
    }
}

fn label(v: f64) -> String {
    if v.abs() >= 100.0 || v == 0.0 {
        format!("{v:.0}")
    } else if v.abs() >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.3}")
    }
}

/// A plot of `series` with axis titles; `log_x` plots x on a log10 scale.
pub fn plot(title: &str, x_title: &str, y_title: &str, series: &[Series], log_x: bool) -> RgbImage {
    let mut img = RgbImage::new(W as u32, H as u32);
    img.data.iter_mut().for_each(|v| *v = 1.0);
    let tx = |x: f64| if log_x { x.max(1e-12).log10() } else { x };
    let pts = series
        .iter()
        .flat_map(|s| s.points.iter())
        .filter(|p| p.0.is_finite() && p.1.is_finite());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts {
        (x0, x1, y0, y1) = (x0.min(tx(x)), x1.max(tx(x)), y0.min(y), y1.max(y));
    }
    if x0 > x1 {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    let (px, py) = ((x1 - x0).max(1e-9) * 0.05, (y1 - y0).max(1e-9) * 0.08);
    let (x0, x1, y0, y1) = (x0 - px, x1 + px, y0 - py, y1 + py);
    let sx = |x: f64| LEFT + ((tx(x) - x0) / (x1 - x0) * (W - LEFT - RIGHT) as f64) as i32;
    let sy = |y: f64| H - BOTTOM - ((y - y0) / (y1 - y0) * (H - TOP - BOTTOM) as f64) as i32;
    let grey = [0.85, 0.85, 0.85];
    let black = [0.0, 0.0, 0.0];
    for i in 0..=5 {
        let fx = x0 + (x1 - x0) * i as f64 / 5.0;
        let fy = y0 + (y1 - y0) * i as f64 / 5.0;
        let xv = if log_x { 10f64.powf(fx) } else { fx };
        let (gx, gy) = (sx(xv), sy(fy));
        line(&mut img, (gx, TOP), (gx, H - BOTTOM), grey);
        line(&mut img, (LEFT, gy), (W - RIGHT, gy), grey);
        let lx = label(xv);
        text(
            &mut img,
            gx - 3 * lx.len() as i32,
            H - BOTTOM + 6,
            &lx,
            black,
        );
        let ly = label(fy);
        text(&mut img, LEFT - 6 - 6 * ly.len() as i32, gy - 3, &ly, black);
    }
    line(&mut img, (LEFT, H - BOTTOM), (W - RIGHT, H - BOTTOM), black);
    line(&mut img, (LEFT, TOP), (LEFT, H - BOTTOM), black);
    text(&mut img, LEFT, 10, title, black);
    text(
        &mut img,
        (W - 6 * x_title.len() as i32) / 2,
        H - 18,
        x_title,
        black,
    );
    text(&mut img, 4, TOP - 14, y_title, black);
    for (k, s) in series.iter().enumerate() {
        let p: Vec<(i32, i32)> = s
            .points
            .iter()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .map(|&(x, y)| (sx(x), sy(y)))
            .collect();
        if s.line {
            for w in p.windows(2) {
                line(&mut img, w[0], w[1], s.colour);
            }
        }
        for &(x, y) in &p {
            for dy in -s.marker..=s.marker {
                for dx in -s.marker..=s.marker {
                    put(&mut img, x + dx, y + dy, s.colour);
                }
            }
        }
        let finite = s
            .points
            .iter()
            .zip(&s.labels)
            .filter(|(p, _)| p.0.is_finite() && p.1.is_finite());
        for ((x, y), l) in finite {
            text(&mut img, sx(*x) + s.marker + 2, sy(*y) - 10, l, s.colour);
        }
        let ly = TOP + 6 + 12 * k as i32;
        for dx in 0..10 {
            for dy in 0..3 {
                put(&mut img, W - RIGHT + 10 + dx, ly + 2 + dy, s.colour);
            }
        }
        text(&mut img, W - RIGHT + 25, ly, &s.label, black);
    }
    img
}

/// Indices of the points on the Pareto front (lower x and higher y are better).
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].0.is_finite() && points[i].1.is_finite())
        .collect();
    idx.sort_by(|&a, &b| {
        points[a]
            .0
            .total_cmp(&points[b].0)
            .then(points[b].1.total_cmp(&points[a].1))
    });
    let mut front = Vec::new();
    let mut best = f64::MIN;
    for i in idx {
        if points[i].1 > best {
            best = points[i].1;
            front.push(i);
        }
    }
    front
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_keeps_only_undominated_points() {
        let p = [
            (1.0, 20.0),
            (2.0, 25.0),
            (3.0, 24.0),
            (4.0, 30.0),
            (0.5, 10.0),
        ];
        assert_eq!(pareto_front(&p), vec![4, 0, 1, 3]);
    }

    #[test]
    fn plot_draws_something() {
        let s = Series {
            label: "a".into(),
            colour: [1.0, 0.0, 0.0],
            points: vec![(1.0, 1.0), (2.0, 3.0)],
            line: true,
            marker: 2,
            labels: Vec::new(),
        };
        let img = plot("t", "x", "y", &[s], false);
        assert!(img.data.chunks(3).any(|c| c == [1.0, 0.0, 0.0]));
    }
}
